"""Effects in the output path: what the sensor does to the state it reads.

Each enters the outputs directly (no state equation): an offset (bias), a gain error, a sensor blind
to the sign (|h|, e.g. a speed pickup), clipping at the measured extreme. Quantisation is noise, not
an effect: it is noted, never added.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from greyfit.schemas.model import Model
from greyfit.solvers.discovery.augment import fresh_name, rewrite_output, with_parameter
from greyfit.solvers.discovery.candidate import Candidate, LibraryContext, OutputFit, fmt
from greyfit.solvers.discovery.families.base import Scope, bind


class _SensorFamily:
    name = ""
    scope: Scope = "output"
    generic = False

    def supports(self, ctx: LibraryContext) -> bool:
        return ctx.outputs is not None

    def candidates(self, ctx: LibraryContext) -> list[Candidate]:
        assert ctx.outputs is not None   # supports() said so
        out: list[Candidate] = []
        for j, name in enumerate(ctx.outputs.names):
            measured = measured_values(ctx.outputs, j)
            if measured.size:
                out += self.for_output(ctx, j, name, [f[j] for f in ctx.outputs.fitted], measured)
        return out

    def for_output(self, ctx, j, name, y_hat, measured) -> list[Candidate]:
        raise NotImplementedError


class OutputOffset(_SensorFamily):
    name = "output_offset"

    def rewrite(self, model: Model, **spec: Any) -> tuple[Model, list[str]]:
        b = fresh_name(model, f"{spec['output']}_bias")
        model = with_parameter(model, b, 0.0)
        return rewrite_output(model, spec["output"], "{h} + " + b), [b]

    def for_output(self, ctx, j, name, y_hat, measured) -> list[Candidate]:
        step = quantisation_step(measured)
        if step is not None:
            ctx.notes.append(f"output {name} is quantised in steps of {fmt(step)}: treated as noise "
                             f"(variance step²/12 = {fmt(step ** 2 / 12)}), not as an effect")
        return [Candidate(self.name, {}, f"{name} = h + {name}_bias", f"constant offset (bias) of the sensor of {name}",
                          bind(self, output=name), outputs={j: [np.ones_like(y) for y in y_hat]},
                          family=f"output_offset:{name}")]


class OutputGain(_SensorFamily):
    name = "output_gain"

    def rewrite(self, model: Model, **spec: Any) -> tuple[Model, list[str]]:
        g = fresh_name(model, f"{spec['output']}_gain_error")
        model = with_parameter(model, g, 0.0)
        return rewrite_output(model, spec["output"], "(1 + " + g + ")*{h}"), [g]

    def for_output(self, ctx, j, name, y_hat, measured) -> list[Candidate]:
        return [Candidate(self.name, {}, f"{name} = (1 + {name}_gain_error)*h", f"gain error of the sensor of {name}",
                          bind(self, output=name), outputs={j: [y.copy() for y in y_hat]},
                          family=f"output_gain:{name}")]


class OutputAbs(_SensorFamily):
    """The measurement never goes below zero and sits at zero now and then, like |h| does. Scored as
    h + β(|h| − h), β = 1 being |h|, where the fitted h changes sign; where it does not (the fit
    collapsed onto the mean of |h|) the linearisation is blind and a refit decides."""

    name = "output_abs"

    def rewrite(self, model: Model, **spec: Any) -> tuple[Model, list[str]]:
        return rewrite_output(model, spec["output"], "abs({h})"), []

    def for_output(self, ctx, j, name, y_hat, measured) -> list[Candidate]:
        if not sign_blind(measured):
            return []
        changes_sign = np.mean(np.concatenate(y_hat) < 0) > 0.02
        return [Candidate(self.name, {}, f"{name} = abs(h)",
                          f"the sensor of {name} does not see the sign: it measures |h|",
                          bind(self, output=name),
                          outputs={j: [np.abs(y) - y if changes_sign else np.zeros_like(y) for y in y_hat]},
                          sign=1.0, family=f"output_abs:{name}", refit_only=not changes_sign, fresh_start=True)]


class OutputSaturation(_SensorFamily):
    """A clipped sensor sits on its limit for a while, where the model goes past it."""

    name = "output_saturation"

    def rewrite(self, model: Model, **spec: Any) -> tuple[Model, list[str]]:
        return rewrite_output(model, spec["output"], f"{spec['fn']}({{h}}, {fmt(spec['level'])})"), []

    def for_output(self, ctx, j, name, y_hat, measured) -> list[Candidate]:
        out = []
        allhat = np.concatenate(y_hat)
        spread = float(measured.max() - measured.min()) or 1.0
        for side, level in (("upper", measured.max()), ("lower", measured.min())):
            at_level = np.mean(np.abs(measured - level) <= 1e-6 * spread)
            beyond = (allhat > level) if side == "upper" else (allhat < level)
            if at_level < 0.01 or not beyond.any():
                continue
            fn = "min" if side == "upper" else "max"
            change = [(np.minimum(y, level) if side == "upper" else np.maximum(y, level)) - y for y in y_hat]
            out.append(Candidate(self.name, {}, f"{name} = {fn}(h, {fmt(level)})",
                                 f"the sensor of {name} clips at {fmt(level)} ({side} limit)",
                                 bind(self, output=name, fn=fn, level=float(level)), outputs={j: change}, sign=1.0,
                                 family=f"output_saturation:{name}:{side}"))
        return out


def measured_values(outputs: OutputFit, j: int) -> np.ndarray:
    return np.concatenate([d.y[j][np.isfinite(d.y[j])] for d in outputs.data])


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
