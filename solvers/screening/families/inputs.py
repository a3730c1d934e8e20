"""What happens to an input before it acts: it saturates, it passes through a dead zone, or it acts
whole samples late."""
from __future__ import annotations

from typing import Any

import numpy as np

from greyfit.schemas.model import Model
from greyfit.solvers.screening.augment import fresh_name, replace_parameter, with_parameter
from greyfit.solvers.screening.candidate import Candidate, LibraryContext, fmt
from greyfit.solvers.screening.families.base import Scope, bind, sensitivity_regressor

MAX_LAG = 20   # samples


def _input_regressor(ctx: LibraryContext, k: int, change: list[np.ndarray]):
    return sensitivity_regressor(ctx.trace, ctx.trace.ju, k, change)


class NeedsInputs:
    """The `supports` of a family that changes an input: it has something to look at when the model has inputs."""

    def supports(self, ctx: LibraryContext) -> bool:
        """Whether the model has inputs.

        Parameters
        ----------
        ctx : LibraryContext
            The model, the fitted trajectory and the discovery options.

        Returns
        -------
        bool
            True when the model has inputs.
        """
        return bool(ctx.trace.cm.inputs)


class Saturation(NeedsInputs):
    name = "saturation"
    scope: Scope = "input"
    generic = False

    def rewrite(self, model: Model, **spec: Any) -> tuple[Model, list[str]]:
        """`model` with input u replaced by min(max(u, −u_max), u_max), u_max a new parameter.

        Parameters
        ----------
        model : Model
            The model to rewrite (not changed: a copy is returned).
        **spec : Any
            `input`: the input's name; `level`: the start value of u_max (≥ 0).

        Returns
        -------
        tuple of (Model, list of str)
            The rewritten model and the new parameter's name.

        Raises
        ------
        ModelDefinitionError
            When a rewritten expression does not parse.
        """
        u, level = spec["input"], spec["level"]
        name = fresh_name(model, f"{u}_max")
        model = with_parameter(model, name, float(level), lower=0.0)
        return replace_parameter(model, u, f"min(max({u}, -{name}), {name})"), [name]

    def candidates(self, ctx: LibraryContext) -> list[Candidate]:
        """Saturation of every input at 13 levels between the median and the 98th percentile of |u|.

        Parameters
        ----------
        ctx : LibraryContext
            The model, the fitted trajectory and the discovery options.

        Returns
        -------
        list of Candidate
            Per input and level, a candidate whose regressor is the change clip(u) − u through ∂f/∂u
            (levels where no traced equation feels the change are left out).
        """
        out: list[Candidate] = []
        for k, u in enumerate(ctx.trace.cm.inputs):
            vals = ctx.input_values(u)
            mags = np.abs(np.concatenate(vals))
            if mags.max() <= 0:
                continue
            for level in np.unique(np.quantile(mags, np.linspace(0.5, 0.98, 13))):
                if level <= 0:
                    continue
                reg = _input_regressor(ctx, k, [np.clip(x, -level, level) - x for x in vals])
                if reg:
                    out.append(Candidate(self.name, reg, f"{u} -> min(max({u}, -{u}_max), {u}_max)",
                                         f"input {u} saturates near ±{fmt(level)}",
                                         bind(self, input=u, level=float(level)), sign=1.0,
                                         family=f"saturation:{u}", variables=(u,)))
        return out


class DeadZone(NeedsInputs):
    """An input that acts only beyond a band: a valve or an actuator with a dead zone, u replaced by
    u − min(max(u, −w), w) (0 inside ±w, u ∓ w outside). The declared gain on u stays the gain beyond
    the band; a model without the band can only lower that gain and add an offset to fit it."""

    name = "dead_zone"
    scope: Scope = "input"
    generic = False

    def rewrite(self, model: Model, **spec: Any) -> tuple[Model, list[str]]:
        """`model` with input u replaced by u − min(max(u, −w), w), w a new parameter (the band's half-width).

        Parameters
        ----------
        model : Model
            The model to rewrite (not changed: a copy is returned).
        **spec : Any
            `input`: the input's name; `level`: the start value of w (> 0).

        Returns
        -------
        tuple of (Model, list of str)
            The rewritten model and the new parameter's name.

        Raises
        ------
        ModelDefinitionError
            When a rewritten expression does not parse.
        """
        u, level = spec["input"], spec["level"]
        name = fresh_name(model, f"{u}_dead")
        model = with_parameter(model, name, float(level), lower=0.0)
        return replace_parameter(model, u, f"({u} - min(max({u}, -{name}), {name}))"), [name]

    def candidates(self, ctx: LibraryContext) -> list[Candidate]:
        """A dead zone of every input at 13 half-widths between the 2nd and the 60th percentile of |u|.

        Parameters
        ----------
        ctx : LibraryContext
            The model, the fitted trajectory and the discovery options.

        Returns
        -------
        list of Candidate
            Per input and half-width, a candidate whose regressor is the change −clip(u, −w, w) through
            ∂f/∂u (half-widths where no traced equation feels the change are left out); the refit
            estimates w from the best of them.
        """
        out: list[Candidate] = []
        for k, u in enumerate(ctx.trace.cm.inputs):
            vals = ctx.input_values(u)
            mags = np.abs(np.concatenate(vals))
            if mags.max() <= 0:
                continue
            for level in np.unique(np.quantile(mags, np.linspace(0.02, 0.6, 13))):
                if level <= 0:
                    continue
                reg = _input_regressor(ctx, k, [-np.clip(x, -level, level) for x in vals])
                if reg:
                    out.append(Candidate(self.name, reg, f"{u} -> {u} - min(max({u}, -{u}_dead), {u}_dead)",
                                         f"input {u} acts only beyond a dead zone of ±{fmt(level)}",
                                         bind(self, input=u, level=float(level)), sign=1.0,
                                         family=f"dead_zone:{u}", variables=(u,)))
        return out


class InputDelay(NeedsInputs):
    """The delay is a whole number of samples: the model language has no delay operator, so the
    delayed input enters as data (returned in `added_inputs`)."""

    name = "input_delay"
    scope: Scope = "input"
    generic = True

    def rewrite(self, model: Model, **spec: Any) -> tuple[Model, list[str]]:
        """`model` with input u replaced by a new input, u delayed.

        Parameters
        ----------
        model : Model
            The model to rewrite (not changed: a copy is returned).
        **spec : Any
            `input`: the input's name; `delayed`: the new input's name.

        Returns
        -------
        tuple of (Model, list of str)
            The rewritten model (one more input) and no new parameters; the delayed data come with the
            candidate's `transform_experiments`.

        Raises
        ------
        ModelDefinitionError
            When a rewritten expression does not parse.
        """
        u, delayed = spec["input"], spec["delayed"]
        model = model.model_copy(update={"inputs": [*model.inputs, delayed]})
        return replace_parameter(model, u, delayed), []

    def candidates(self, ctx: LibraryContext) -> list[Candidate]:
        """A delay of every input by 1 to `MAX_LAG` whole samples.

        Parameters
        ----------
        ctx : LibraryContext
            The model, the fitted trajectory and the discovery options.

        Returns
        -------
        list of Candidate
            Per input and lag, a candidate that brings its delayed input as data (`transform_experiments`);
            the refit chooses among the lags.
        """
        out: list[Candidate] = []
        dt = float(np.median(np.diff(ctx.trace.t[0])))
        for k, u in enumerate(ctx.trace.cm.inputs):
            delayed = fresh_name(ctx.model, f"{u}_delayed")
            for lag in range(1, MAX_LAG + 1):
                change = [np.concatenate([np.full(lag, x[0]), x[:-lag]]) - x for x in ctx.input_values(u)]
                reg = _input_regressor(ctx, k, change)
                if not reg:
                    continue
                out.append(Candidate(self.name, reg, f"{u}(t) -> {delayed} = {u}(t - {fmt(lag * dt)})",
                                     f"input {u} acts {lag} sample(s) ({fmt(lag * dt)} s) late",
                                     bind(self, input=u, delayed=delayed), sign=1.0, family=f"input_delay:{u}",
                                     refit_variants=True, generic=True, variables=(u,), lag=lag,
                                     transform_experiments=_delayed_data(u, delayed, lag)))
        return out


def _delayed_data(u: str, delayed: str, lag: int):
    def transform(experiments):
        out_exps = []
        for exp in experiments:
            series = list(exp.inputs[u])
            shifted = [series[0]] * lag + series[:-lag]
            out_exps.append(exp.model_copy(update={"inputs": {**exp.inputs, delayed: shifted}}))
        return out_exps
    return transform
