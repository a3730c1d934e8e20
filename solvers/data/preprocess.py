"""Per-experiment preparation: window, detrend, decimate with a zero-phase anti-alias filter; hints.

Everything here is numpy (scipy is only a test extra); the tests compare the filter with
`scipy.signal`.
"""
from __future__ import annotations

import numpy as np

from greyfit.schemas.experiment import Experiment
from greyfit.schemas.fit import FitOptions
from greyfit.schemas.preprocess import ExperimentPreprocessing, Hint, Preprocess, PreprocessingReport
from greyfit.solvers.errors import DataError

FIR_TAPS_PER_FACTOR = 20   # scipy.signal.decimate(ftype="fir") uses the same order, 20 q


def anti_alias_taps(q: int) -> np.ndarray:
    """Low-pass FIR for decimation by q: Hamming-windowed sinc, 20q+1 taps, cut-off 1/q of Nyquist.

    The same design as ``scipy.signal.firwin(20*q + 1, 1/q, window="hamming")`` (unit gain at DC).
    """
    n = FIR_TAPS_PER_FACTOR * q
    k = np.arange(n + 1) - n / 2
    h = np.sinc(k / q) / q * np.hamming(n + 1)
    return h / h.sum()


def zero_phase_filter(x: np.ndarray, taps: np.ndarray) -> np.ndarray:
    """Apply a symmetric (linear-phase) FIR centred on each sample: no delay.

    The ends are extended by odd reflection about the first and last sample (as `filtfilt` does),
    so that a trend does not bend at the edges.
    """
    half = (taps.size - 1) // 2
    left = 2 * x[0] - x[half:0:-1]
    right = 2 * x[-1] - x[-2:-half - 2:-1]
    return np.convolve(np.concatenate([left, x, right]), taps, mode="valid")


def _uniform_step(t: np.ndarray, where: str) -> float:
    steps = np.diff(t)
    dt = float(np.median(steps))
    if np.max(np.abs(steps - dt)) > 1e-6 * dt:
        raise DataError("decimate needs uniform sampling; the time steps vary "
                        f"(from {steps.min():g} to {steps.max():g}); resample the record first", where)
    return dt


def _trend(t: np.ndarray, y: np.ndarray, kind: str) -> tuple[np.ndarray, list[float]]:
    ok = np.isfinite(y)
    if kind == "mean":
        m = float(np.mean(y[ok]))
        return np.full_like(y, m), [m]
    tt = t - t[0]
    slope, intercept = np.polyfit(tt[ok], y[ok], 1)
    return intercept + slope * tt, [float(intercept), float(slope)]


def preprocess_experiment(exp: Experiment, where: str) -> tuple[Experiment, ExperimentPreprocessing]:
    """The experiment with its `preprocess` applied (and removed), and a report of what was done."""
    spec: Preprocess = exp.preprocess
    t = np.asarray(exp.time, dtype=float)
    series = {("inputs", k): np.array(v, dtype=float) for k, v in exp.inputs.items()}
    series.update({("outputs", k): np.array(v, dtype=float) for k, v in exp.outputs.items()})
    series.update({("derivatives", k): np.array(v, dtype=float) for k, v in exp.derivatives.items()})
    for (group, name), values in series.items():
        if values.size != t.size:
            raise DataError(f"{values.size} values, time has {t.size}; give one value per time sample",
                            f"{where}.{group}.{name}")
    report = ExperimentPreprocessing(name=exp.name, samples_in=t.size, samples_out=t.size)
    if spec.window is not None:
        keep = (t >= spec.window[0]) & (t <= spec.window[1])
        if keep.sum() < 2:
            raise DataError(f"window {list(spec.window)} keeps {int(keep.sum())} samples of a record from "
                            f"{t[0]:g} to {t[-1]:g}; widen it", f"{where}.preprocess.window")
        t = t[keep]
        series = {k: v[keep] for k, v in series.items()}
        report.window = spec.window
    if spec.detrend is not None:
        if spec.detrend == "linear" and exp.derivatives:
            raise DataError("a linear detrend would change the derivatives' meaning; use detrend 'mean' "
                            "or leave derivatives out (they are then estimated)", f"{where}.preprocess.detrend")
        for key in [k for k in series if k[0] != "derivatives"]:
            trend, removed = _trend(t, series[key], spec.detrend)
            series[key] = series[key] - trend
            report.removed_trend[f"{key[0]}.{key[1]}"] = removed
        report.detrend = spec.detrend
    if spec.decimate is not None:
        q = spec.decimate
        _uniform_step(t, f"{where}.time")
        taps = anti_alias_taps(q)
        if t.size <= taps.size:
            raise DataError(f"decimate {q} needs more than {taps.size} samples (the anti-alias filter's "
                            f"length); the record has {t.size}", f"{where}.preprocess.decimate")
        for (group, name), values in series.items():
            if not np.all(np.isfinite(values)):
                raise DataError("decimate needs complete series; this one has missing samples (null): "
                                "fill or window them out", f"{where}.{group}.{name}")
            series[(group, name)] = zero_phase_filter(values, taps)[::q]
        t = t[::q]
        report.decimate = q
        report.anti_alias_filter = (f"zero-phase FIR, {taps.size} taps (Hamming-windowed sinc), "
                                    f"cut-off {1 / q:g} of the original Nyquist frequency")
    report.samples_out = t.size
    data = exp.model_dump()
    data["preprocess"] = None
    data["time"] = t.tolist()
    for (group, name), values in series.items():
        data[group][name] = [None if not np.isfinite(v) else float(v) for v in values]
    return Experiment.model_validate(data), report


def looks_piecewise_constant(u: np.ndarray) -> bool:
    """True for PRBS, steps and other held signals: mostly exact repeats, few levels."""
    u = u[np.isfinite(u)]
    span = float(np.ptp(u)) if u.size else 0.0
    if u.size < 10 or span == 0:
        return False
    flat = float(np.mean(np.abs(np.diff(u)) <= 1e-9 * span))
    if flat >= 0.8 or flat < 0.3:
        return flat >= 0.8
    return bool(np.unique(np.round(u / (1e-6 * span))).size <= 10)


def input_hints(experiments: list[Experiment], options: FitOptions) -> list[Hint]:
    """A hint per input that looks piecewise constant while inputs are interpolated linearly."""
    if options.input_interpolation != "foh":
        return []
    held = sorted({name for exp in experiments for name, values in exp.inputs.items()
                   if looks_piecewise_constant(np.array(values, dtype=float))})
    if not held:
        return []
    return [Hint(code="input_looks_held",
                 message=f"input(s) {held} look piecewise constant (PRBS, steps) but "
                         "options.input_interpolation is 'foh', which ramps between samples; "
                         "if the input is held between samples set input_interpolation to 'zoh'",
                 detail={"inputs": held})]


def preprocess_experiments(experiments: list[Experiment], field: str = "experiments",
                           ) -> tuple[list[Experiment], list[ExperimentPreprocessing]]:
    """Apply each experiment's `preprocess`; experiments without one pass unchanged."""
    out, reports = [], []
    for i, exp in enumerate(experiments):
        if exp.preprocess is None:
            out.append(exp)
            continue
        new, report = preprocess_experiment(exp, f"{field}[{i}]")
        out.append(new)
        reports.append(report)
    return out, reports


def preprocessing_report(reports: list[ExperimentPreprocessing], hints: list[Hint]) -> PreprocessingReport | None:
    return PreprocessingReport(experiments=reports, hints=hints) if reports or hints else None


def prepare_request(request):
    """(request with every `preprocess` applied to its experiments and validation records, report).

    Works for any request with `experiments`, `validation` (optional) and `options`.
    """
    experiments, reports = preprocess_experiments(request.experiments, "experiments")
    update = {"experiments": experiments}
    validation = getattr(request, "validation", None)
    if validation:
        update["validation"], more = preprocess_experiments(validation, "validation")
        reports += more
    hints = input_hints(experiments + list(update.get("validation", [])), request.options)
    changed = any(r is not None for r in reports)
    return (request.model_copy(update=update) if changed else request), preprocessing_report(reports, hints)
