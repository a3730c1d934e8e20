"""Effects in the output path: what the sensor does to the state it reads.

Each enters the outputs directly (no state equation): an offset (bias), a gain error, a sensor blind
to the sign (|h|, e.g. a speed pickup), clipping at the measured extreme. Quantisation is noise, not
an effect: it is noted, never added.
"""
from __future__ import annotations

import numpy as np

from greyfit.schemas.model import Model
from greyfit.solvers.data.experiments import ExperimentData
from greyfit.solvers.discovery.augment import fresh_name, rewrite_output, with_parameter
from greyfit.solvers.discovery.effects import Candidate, _fmt

OUTPUT_EFFECTS = ("output_offset", "output_gain", "output_abs", "output_saturation")


def output_effects(model: Model, outputs: list[str], fitted: list[np.ndarray], data: list[ExperimentData],
                   effects: list[str]) -> tuple[list[Candidate], list[str]]:
    """Candidates for every output; `fitted[e]` is (ny, n) of the fitted model's outputs."""
    out: list[Candidate] = []
    notes: list[str] = []
    for j, name in enumerate(outputs):
        y_hat = [f[j] for f in fitted]
        measured = np.concatenate([d.y[j][np.isfinite(d.y[j])] for d in data])
        if measured.size == 0:
            continue
        step = quantisation_step(measured)
        if step is not None:
            notes.append(f"output {name} is quantised in steps of {_fmt(step)}: treated as noise "
                         f"(variance step²/12 = {_fmt(step ** 2 / 12)}), not as an effect")
        if "output_offset" in effects:
            def apply_offset(m: Model, name=name) -> tuple[Model, list[str]]:
                b = fresh_name(m, f"{name}_bias")
                m = with_parameter(m, b, 0.0)
                return rewrite_output(m, name, "{h} + " + b), [b]
            out.append(Candidate("output_offset", {}, f"{name} = h + {name}_bias",
                                 f"constant offset (bias) of the sensor of {name}", apply_offset,
                                 outputs={j: [np.ones_like(y) for y in y_hat]}, family=f"output_offset:{name}"))
        if "output_gain" in effects:
            def apply_gain(m: Model, name=name) -> tuple[Model, list[str]]:
                g = fresh_name(m, f"{name}_gain_error")
                m = with_parameter(m, g, 0.0)
                return rewrite_output(m, name, "(1 + " + g + ")*{h}"), [g]
            out.append(Candidate("output_gain", {}, f"{name} = (1 + {name}_gain_error)*h",
                                 f"gain error of the sensor of {name}", apply_gain,
                                 outputs={j: [y.copy() for y in y_hat]}, family=f"output_gain:{name}"))
        allhat = np.concatenate(y_hat)
        if "output_abs" in effects and sign_blind(measured):
            # the measurement never goes below zero and sits at zero now and then, like |h| does.
            # Scored as h + β(|h| − h), β = 1 being |h|, where the fitted h changes sign; where it does
            # not (the fit collapsed onto the mean of |h|) the linearisation is blind and a refit decides.
            def apply_abs(m: Model, name=name) -> tuple[Model, list[str]]:
                return rewrite_output(m, name, "abs({h})"), []
            changes_sign = np.mean(allhat < 0) > 0.02
            out.append(Candidate("output_abs", {}, f"{name} = abs(h)",
                                 f"the sensor of {name} does not see the sign: it measures |h|", apply_abs,
                                 outputs={j: [np.abs(y) - y if changes_sign else np.zeros_like(y) for y in y_hat]},
                                 sign=1.0, family=f"output_abs:{name}", refit_only=not changes_sign,
                                 fresh_start=True))
        if "output_saturation" in effects:
            for side, level in (("upper", measured.max()), ("lower", measured.min())):
                spread = float(measured.max() - measured.min()) or 1.0
                at_level = np.mean(np.abs(measured - level) <= 1e-6 * spread)
                beyond = (allhat > level) if side == "upper" else (allhat < level)
                if at_level < 0.01 or not beyond.any():
                    continue   # a clipped sensor sits on its limit for a while, where the model goes past it
                fn = "min" if side == "upper" else "max"
                change = [(np.minimum(y, level) if side == "upper" else np.maximum(y, level)) - y for y in y_hat]

                def apply_clip(m: Model, name=name, fn=fn, level=level) -> tuple[Model, list[str]]:
                    return rewrite_output(m, name, f"{fn}({{h}}, {_fmt(level)})"), []
                out.append(Candidate("output_saturation", {}, f"{name} = {fn}(h, {_fmt(level)})",
                                     f"the sensor of {name} clips at {_fmt(level)} ({side} limit)", apply_clip,
                                     outputs={j: change}, sign=1.0, family=f"output_saturation:{name}:{side}"))
    return out, notes


def sign_blind(measured: np.ndarray) -> bool:
    """Nearly never negative, and down at zero (within the noise) at times: the look of |h|."""
    spread = float(np.ptp(measured))
    if spread <= 0 or np.mean(measured < 0) > 0.01:
        return False
    return bool(np.mean(measured < 0.03 * spread) >= 0.01)


def quantisation_step(values: np.ndarray) -> float | None:
    """The step of a quantised signal (every value on a grid of few levels per range), else None."""
    levels = np.unique(values)
    if levels.size < 3 or levels.size > values.size / 4:
        return None
    step = float(np.min(np.diff(levels)))
    spread = float(levels[-1] - levels[0])
    if step <= 0 or spread / step > 1e6:
        return None
    on_grid = np.abs((values - levels[0]) / step - np.round((values - levels[0]) / step))
    return step if np.all(on_grid < 1e-6) else None
