"""Effects in the output path: what the sensor does to the state it reads.

Each enters the outputs directly (no state equation): an offset (bias), a gain error, a sensor blind
to the sign (|h|, e.g. a speed pickup), clipping at the measured extreme. Quantisation is noise, not
an effect: it is noted, never added.
"""
from __future__ import annotations

import re
from typing import Any

import numpy as np

from greyfit.schemas.model import Model
from greyfit.solvers.screening.augment import fresh_name, rewrite_output, with_parameter
from greyfit.solvers.screening.candidate import Candidate, LibraryContext, OutputFit, fmt
from greyfit.solvers.screening.families.base import Scope, bind

_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")


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
        """Output h becomes h + b, b a new parameter (the sensor's bias).

        Parameters
        ----------
        model : Model
            The model to rewrite (not changed: a copy is returned).
        **spec : Any
            `output`: the measured output's name.

        Returns
        -------
        tuple of (Model, list of str)
            The rewritten model and the new parameter's name.
        """
        b = fresh_name(model, f"{spec['output']}_bias")
        model = with_parameter(model, b, 0.0)
        return rewrite_output(model, spec["output"], "{h} + " + b), [b]

    def for_output(self, ctx, j, name, y_hat, measured) -> list[Candidate]:
        """The candidate bias of this output (a constant column); notes a quantised output.

        Parameters
        ----------
        ctx : LibraryContext
            The model, the fitted trajectory and options; notes go to `ctx.notes`.
        j : int
            Index of the output.
        name : str
            The output's name.
        y_hat : list of numpy.ndarray
            The fitted output, one (n_e,) array per experiment.
        measured : numpy.ndarray
            The finite measured samples of the output, all experiments together.

        Returns
        -------
        list of Candidate
            One candidate.
        """
        step = quantisation_step(measured)
        if step is not None:
            ctx.notes.append(f"output {name} is quantised in steps of {fmt(step)}: treated as noise "
                             f"(variance step²/12 = {fmt(step ** 2 / 12)}), not as an effect")
        return [Candidate(self.name, {}, f"{name} = {reading(ctx, name)} + {name}_bias",
                          f"constant offset (bias) of the sensor of {name}",
                          bind(self, output=name), outputs={j: [np.ones_like(y) for y in y_hat]},
                          family=f"output_offset:{name}")]


class OutputGain(_SensorFamily):
    name = "output_gain"

    def rewrite(self, model: Model, **spec: Any) -> tuple[Model, list[str]]:
        """Output h becomes (1 + g)·h, g a new parameter (the sensor's gain error).

        Parameters
        ----------
        model : Model
            The model to rewrite (not changed: a copy is returned).
        **spec : Any
            `output`: the measured output's name.

        Returns
        -------
        tuple of (Model, list of str)
            The rewritten model and the new parameter's name.
        """
        g = fresh_name(model, f"{spec['output']}_gain_error")
        model = with_parameter(model, g, 0.0)
        return rewrite_output(model, spec["output"], "(1 + " + g + ")*{h}"), [g]

    def for_output(self, ctx, j, name, y_hat, measured) -> list[Candidate]:
        """The candidate gain error of this output (the fitted output as its column).

        Parameters
        ----------
        ctx : LibraryContext
            The model, the fitted trajectory and options; notes go to `ctx.notes`.
        j : int
            Index of the output.
        name : str
            The output's name.
        y_hat : list of numpy.ndarray
            The fitted output, one (n_e,) array per experiment.
        measured : numpy.ndarray
            The finite measured samples of the output, all experiments together.

        Returns
        -------
        list of Candidate
            One candidate.
        """
        return [Candidate(self.name, {}, f"{name} = (1 + {name}_gain_error)*{reading(ctx, name)}",
                          f"gain error of the sensor of {name}",
                          bind(self, output=name), outputs={j: [y.copy() for y in y_hat]},
                          family=f"output_gain:{name}")]


class OutputAbs(_SensorFamily):
    """The measurement never goes below zero and sits at zero now and then, like |h| does. Scored as
    h + β(|h| − h), β = 1 being |h|, where the fitted h changes sign; where it does not (the fit
    collapsed onto the mean of |h|) the linearisation is blind and a refit decides."""

    name = "output_abs"

    def rewrite(self, model: Model, **spec: Any) -> tuple[Model, list[str]]:
        """Output h becomes |h|.

        Parameters
        ----------
        model : Model
            The model to rewrite (not changed: a copy is returned).
        **spec : Any
            `output`: the measured output's name.

        Returns
        -------
        tuple of (Model, list of str)
            The rewritten model and no new parameters.
        """
        return rewrite_output(model, spec["output"], "abs({h})"), []

    def for_output(self, ctx, j, name, y_hat, measured) -> list[Candidate]:
        """The candidate |h| where the measurement looks sign-blind (`sign_blind`).

        Parameters
        ----------
        ctx : LibraryContext
            The model, the fitted trajectory and options; notes go to `ctx.notes`.
        j : int
            Index of the output.
        name : str
            The output's name.
        y_hat : list of numpy.ndarray
            The fitted output, one (n_e,) array per experiment.
        measured : numpy.ndarray
            The finite measured samples of the output, all experiments together.

        Returns
        -------
        list of Candidate
            One candidate (refit only when the fitted output keeps its sign), or none.
        """
        if not sign_blind(measured):
            return []
        changes_sign = np.mean(np.concatenate(y_hat) < 0) > 0.02
        return [Candidate(self.name, {}, f"{name} = abs({reading(ctx, name, bare=True)})",
                          f"the sensor of {name} does not see the sign: it measures |{reading(ctx, name, bare=True)}|",
                          bind(self, output=name),
                          outputs={j: [np.abs(y) - y if changes_sign else np.zeros_like(y) for y in y_hat]},
                          sign=1.0, family=f"output_abs:{name}", refit_only=not changes_sign, fresh_start=True)]


class OutputSaturation(_SensorFamily):
    """A clipped sensor sits on its limit for a while, where the model goes past it."""

    name = "output_saturation"

    def rewrite(self, model: Model, **spec: Any) -> tuple[Model, list[str]]:
        """Output h becomes min(h, level) or max(h, level).

        Parameters
        ----------
        model : Model
            The model to rewrite (not changed: a copy is returned).
        **spec : Any
            `output`: the output's name; `fn`: "min" (upper limit) or "max" (lower limit); `level`: the limit.

        Returns
        -------
        tuple of (Model, list of str)
            The rewritten model and no new parameters.
        """
        return rewrite_output(model, spec["output"], f"{spec['fn']}({{h}}, {fmt(spec['level'])})"), []

    def for_output(self, ctx, j, name, y_hat, measured) -> list[Candidate]:
        """Clipping at the measured maximum and minimum, where the data sit on them and the fit goes past.

        Parameters
        ----------
        ctx : LibraryContext
            The model, the fitted trajectory and options; notes go to `ctx.notes`.
        j : int
            Index of the output.
        name : str
            The output's name.
        y_hat : list of numpy.ndarray
            The fitted output, one (n_e,) array per experiment.
        measured : numpy.ndarray
            The finite measured samples of the output, all experiments together.

        Returns
        -------
        list of Candidate
            Up to two candidates (upper and lower limit).
        """
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
            out.append(Candidate(self.name, {}, f"{name} = {fn}({reading(ctx, name, bare=True)}, {fmt(level)})",
                                 f"the sensor of {name} clips at {fmt(level)} ({side} limit)",
                                 bind(self, output=name, fn=fn, level=float(level)), outputs={j: change}, sign=1.0,
                                 family=f"output_saturation:{name}:{side}"))
        return out


def reading(ctx: LibraryContext, name: str, bare: bool = False) -> str:
    """What output `name` reads, as the model declares it (parenthesised unless one name or `bare`).

    Parameters
    ----------
    ctx : LibraryContext
        The model.
    name : str
        The output's name.
    bare : bool
        True where the text goes inside a function's parentheses.

    Returns
    -------
    str
        The output's expression (`x1`, `(k*x1 + x2)`), or `name` when the model does not declare it.
    """
    text = ctx.model.measured_outputs().get(name, name).strip()
    return text if bare or _NAME.fullmatch(text) else f"({text})"


def measured_values(outputs: OutputFit, j: int) -> np.ndarray:
    """The finite measured samples of output j, all experiments together.

    Parameters
    ----------
    outputs : OutputFit
        The fitted outputs and the experiments' data.
    j : int
        Index of the output.

    Returns
    -------
    numpy.ndarray
        (n,) the samples that are not NaN, experiments concatenated.
    """
    return np.concatenate([d.y[j][np.isfinite(d.y[j])] for d in outputs.data])


def sign_blind(measured: np.ndarray) -> bool:
    """Nearly never negative, and down at zero (within the noise) at times: the look of |h|.

    Parameters
    ----------
    measured : numpy.ndarray
        The measured samples of one output.

    Returns
    -------
    bool
        True when at most 1 % of the samples are negative and at least 1 % are below 3 % of the range.
    """
    spread = float(np.ptp(measured))
    if spread <= 0 or np.mean(measured < 0) > 0.01:
        return False
    return bool(np.mean(measured < 0.03 * spread) >= 0.01)


def quantisation_step(values: np.ndarray) -> float | None:
    """The step of a quantised signal (every value on a grid of few levels per range), else None.

    Parameters
    ----------
    values : numpy.ndarray
        The measured samples of one output.

    Returns
    -------
    float or None
        The smallest difference between levels when every sample lies on that grid and there are at
        least 3 and at most n/4 levels; else None.
    """
    levels = np.unique(values)
    if levels.size < 3 or levels.size > values.size / 4:
        return None
    step = float(np.min(np.diff(levels)))
    spread = float(levels[-1] - levels[0])
    if step <= 0 or spread / step > 1e6:
        return None
    on_grid = np.abs((values - levels[0]) / step - np.round((values - levels[0]) / step))
    return step if np.all(on_grid < 1e-6) else None
