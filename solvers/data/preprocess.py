"""Per-experiment preparation: window, detrend, decimate with a zero-phase anti-alias filter; hints.

Everything here is numpy (scipy is only a test extra); the tests compare the filter with
`scipy.signal`.
"""
from __future__ import annotations

import numpy as np

from greyfit.schemas.experiment import Experiment
from greyfit.schemas.fit import FitOptions
from greyfit.schemas.preprocess import ExperimentPreprocessing, Hint, PreprocessingReport
from greyfit.solvers.data.experiments import series_array
from greyfit.solvers.errors import DataError

FIR_TAPS_PER_FACTOR = 20   # scipy.signal.decimate(ftype="fir") uses the same order, 20 q


def anti_alias_taps(q: int) -> np.ndarray:
    """Low-pass FIR for decimation by q: Hamming-windowed sinc, 20q+1 taps, cut-off 1/q of Nyquist.

    The same design as ``scipy.signal.firwin(20*q + 1, 1/q, window="hamming")`` (unit gain at DC).

    Parameters
    ----------
    q : int
        Decimation factor, ≥ 1.

    Returns
    -------
    numpy.ndarray
        The filter taps, shape (20q + 1,), summing to 1.
    """
    n = FIR_TAPS_PER_FACTOR * q
    k = np.arange(n + 1) - n / 2
    h = np.sinc(k / q) / q * np.hamming(n + 1)
    return h / h.sum()


def zero_phase_filter(x: np.ndarray, taps: np.ndarray) -> np.ndarray:
    """Apply a symmetric (linear-phase) FIR centred on each sample: no delay.

    The ends are extended by odd reflection about the first and last sample (as `filtfilt` does),
    so that a trend does not bend at the edges.

    Parameters
    ----------
    x : numpy.ndarray
        Complete series, shape (N,), longer than half the filter.
    taps : numpy.ndarray
        Symmetric FIR taps of odd length.

    Returns
    -------
    numpy.ndarray
        Filtered series, shape (N,).
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
    """The experiment with its `preprocess` applied (and removed), and a report of what was done.

    Applied in this order: window, detrend (of inputs and outputs), decimate with the zero-phase
    anti-alias filter.

    Parameters
    ----------
    exp : Experiment
        An experiment whose `preprocess` is set.
    where : str
        Field path of the experiment (e.g. ``experiments[0]``), named in the errors.

    Returns
    -------
    experiment : Experiment
        The preprocessed experiment, `preprocess` set to None.
    report : ExperimentPreprocessing
        Samples in and out, the window, the removed trends and the decimation with its filter.

    Raises
    ------
    ValueError
        When `exp.preprocess` is None (a caller's error, not a user's).
    DataError
        When a series' length differs from the time grid's, the window keeps fewer than 2 samples,
        a linear detrend meets given derivatives, or decimation meets non-uniform sampling, a record
        shorter than the filter or missing samples; the field is named.
    """
    spec = exp.preprocess
    if spec is None:   # `preprocess_experiments` passes such experiments through unchanged
        raise ValueError(f"{where} has no preprocess to apply")
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


HELD_REPEATS = 0.5   # fraction of exact repeats from sample to sample above which an input is held


def looks_piecewise_constant(u: np.ndarray) -> bool:
    """True for PRBS, steps and other held signals: mostly exact repeats, or some and few levels.

    A smooth signal sampled and converted to floats practically never repeats a value exactly; a
    digital controller's output updated every k-th sample repeats (k-1)/k of the time whatever its
    levels. A signal held at the sampling rate itself repeats nothing and cannot be recognised.

    Parameters
    ----------
    u : numpy.ndarray
        The input series, NaN where missing, shape (N,).

    Returns
    -------
    bool
        True when at least half the steps repeat the value exactly, or 30-50 % do and the signal has
        at most 10 levels; False for fewer than 10 finite samples or a constant signal.
    """
    u = u[np.isfinite(u)]
    span = float(np.ptp(u)) if u.size else 0.0
    if u.size < 10 or span == 0:
        return False
    flat = float(np.mean(np.abs(np.diff(u)) <= 1e-9 * span))
    if flat >= HELD_REPEATS or flat < 0.3:
        return flat >= HELD_REPEATS
    return bool(np.unique(np.round(u / (1e-6 * span))).size <= 10)


def _variation(u: np.ndarray) -> float:
    """Total variation of a series over its spread: how much it is misread when its interpolation is
    wrong (either mistake is off by |Δu|·Δt/2 over each interval it concerns)."""
    u = u[np.isfinite(u)]
    spread = float(np.std(u)) if u.size > 1 else 0.0
    return float(np.sum(np.abs(np.diff(u)))) / spread if spread > 0 else 0.0


def held_inputs(experiments: list[Experiment]) -> dict[str, tuple[bool, float]]:
    """Per input: (looks piecewise constant in every record that has it, total variation/spread).

    Parameters
    ----------
    experiments : list of Experiment
        The records.

    Returns
    -------
    dict of str to tuple of (bool, float)
        Per input name: whether it looks held in every record, and its total variation over its
        spread summed over the records.
    """
    held: dict[str, tuple[bool, float]] = {}
    for exp in experiments:
        for name, values in exp.inputs.items():
            u = series_array(values)   # None becomes NaN
            looks = looks_piecewise_constant(u)
            was, variation = held.get(name, (True, 0.0))
            held[name] = (was and looks, variation + _variation(u))
    return held


def choose_interpolation(held: dict[str, tuple[bool, float]]) -> tuple[str, dict[str, str], str]:
    """(interpolation for all inputs, the same per input, why) for options.input_interpolation 'auto'.

    One interpolation serves every input of a fit. Where held and smooth inputs are mixed, the one
    that misreads less is chosen: a held input read as a ramp and a smooth one read as held are
    both off by |Δu|·Δt/2 over an interval, the first at its switches only, the second everywhere;
    so the total variation (over the spread) of the inputs each choice misreads decides.

    Parameters
    ----------
    held : dict of str to tuple of (bool, float)
        As `held_inputs` returns.

    Returns
    -------
    mode : str
        ``"zoh"`` or ``"foh"``.
    per_input : dict of str to str
        The same mode for each input.
    why : str
        The reason, for the preprocessing report.
    """
    steps = sorted(n for n, (h, _) in held.items() if h)
    smooth = sorted(n for n, (h, _) in held.items() if not h)
    if not steps or not smooth:
        mode = "zoh" if steps else "foh"
        why = ("every input is piecewise constant (PRBS, steps, a digital output): taken as held (zoh)" if steps
               else "every input varies smoothly: taken as linear between samples (foh)")
        return mode, {name: mode for name in held}, why
    cost_zoh = sum(held[n][1] for n in smooth)   # smooth inputs misread as held
    cost_foh = sum(held[n][1] for n in steps)    # held inputs misread as ramps
    mode = "zoh" if cost_zoh < cost_foh else "foh"
    wrong = smooth if mode == "zoh" else steps
    why = (f"piecewise constant {steps} and smooth {smooth} inputs: one interpolation serves all, and "
           f"{mode} misreads less (total variation over spread {min(cost_zoh, cost_foh):.3g} against "
           f"{max(cost_zoh, cost_foh):.3g}); {wrong} are taken as {'held' if mode == 'zoh' else 'linear'} "
           "although they are not: give them on a finer time grid if that matters")
    return mode, {name: mode for name in held}, why


def input_hints(experiments: list[Experiment], options: FitOptions,
                held: dict[str, tuple[bool, float]] | None = None) -> list[Hint]:
    """A hint per input that looks piecewise constant while inputs are interpolated linearly.

    Parameters
    ----------
    experiments : list of Experiment
        The records.
    options : FitOptions
        The fit options; hints are given only when `input_interpolation` is ``"foh"``.
    held : dict, optional
        `held_inputs(experiments)`, where the caller has it already.

    Returns
    -------
    list of Hint
        One ``input_looks_held`` hint naming every such input, or none.
    """
    if options.input_interpolation != "foh":
        return []
    looking = sorted(name for name, (looks, _) in (held or held_inputs(experiments)).items() if looks)
    if not looking:
        return []
    return [Hint(code="input_looks_held",
                 message=f"input(s) {looking} look piecewise constant (PRBS, steps) but "
                         "options.input_interpolation is 'foh', which ramps between samples; "
                         "if the input is held between samples set input_interpolation to 'zoh' (or 'auto')",
                 detail={"inputs": looking})]


def resolve_interpolation(request, experiments: list[Experiment],
                          held: dict[str, tuple[bool, float]] | None = None):
    """(request with 'auto' replaced by the chosen interpolation, per input, why) — unchanged and
    the requested one per input when the request chose.

    Parameters
    ----------
    request : pydantic.BaseModel
        A request whose `options` has `input_interpolation`.
    experiments : list of Experiment
        The records whose inputs decide (estimation and validation).
    held : dict, optional
        `held_inputs(experiments)`, where the caller has it already.

    Returns
    -------
    request : pydantic.BaseModel
        A copy with the chosen interpolation, or the request itself.
    per_input : dict of str to str
        The interpolation of each input.
    why : str or None
        Why ``auto`` chose as it did; None when the request chose.
    """
    options = request.options
    held = held_inputs(experiments) if held is None else held
    if options.input_interpolation != "auto":
        return request, {n: options.input_interpolation for n in held}, None
    mode, per_input, why = choose_interpolation(held)
    options = options.model_copy(update={"input_interpolation": mode})
    return request.model_copy(update={"options": options}), per_input, why


def preprocess_experiments(experiments: list[Experiment], field: str = "experiments",
                           ) -> tuple[list[Experiment], list[ExperimentPreprocessing]]:
    """Apply each experiment's `preprocess`; experiments without one pass unchanged.

    Parameters
    ----------
    experiments : list of Experiment
        The records.
    field : str, optional
        Field of the request holding them (``experiments`` or ``validation``), for the error paths.

    Returns
    -------
    experiments : list of Experiment
        The records, preprocessed where asked.
    reports : list of ExperimentPreprocessing
        One report per preprocessed record.

    Raises
    ------
    DataError
        As `preprocess_experiment`.
    """
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
    """The preprocessing report, or None when there is nothing to report.

    Parameters
    ----------
    reports : list of ExperimentPreprocessing
        Per-record reports.
    hints : list of Hint
        Hints on the data.

    Returns
    -------
    PreprocessingReport or None
        None when both lists are empty.
    """
    return PreprocessingReport(experiments=reports, hints=hints) if reports or hints else None


def prepare_request(request):
    """(request with every `preprocess` applied to its experiments and validation records and
    `input_interpolation: auto` resolved, report).

    Works for any request with `experiments`, `validation` (optional) and `options`.

    Parameters
    ----------
    request : pydantic.BaseModel
        A fit, simulate or similar request.

    Returns
    -------
    request : pydantic.BaseModel
        The prepared request (the same object when nothing changed).
    report : PreprocessingReport or None
        Per-record reports, hints, and the interpolation of each input with the reason when the
        request's options have `input_interpolation`; else None when there is nothing to report.

    Raises
    ------
    DataError
        As `preprocess_experiment`, with ``experiments[i]`` or ``validation[i]`` in the field.
    """
    experiments, reports = preprocess_experiments(request.experiments, "experiments")
    update = {"experiments": experiments}
    validation = getattr(request, "validation", None)
    if validation:
        update["validation"], more = preprocess_experiments(validation, "validation")
        reports += more
    records = experiments + list(update.get("validation", []))
    # every input converted and judged once (a list of 200 000 numbers costs milliseconds)
    held = held_inputs(records)
    hints = input_hints(records, request.options, held)
    changed = any(r is not None for r in reports)
    prepared = request.model_copy(update=update) if changed else request
    if getattr(request.options, "input_interpolation", None) is None:
        return prepared, preprocessing_report(reports, hints)
    prepared, per_input, why = resolve_interpolation(prepared, records, held)
    return prepared, PreprocessingReport(experiments=reports, hints=hints, input_interpolation=per_input,
                                         interpolation_note=why)
