"""A declared parameter that switches when a state (or a state's difference with an input) exceeds a
threshold: the generic shape of a law the library has no name for (the damper d4 of the LMI-based
identification of physical parameters, which switches with the relative speed |q̇4 − ẇ|)."""
from __future__ import annotations

from typing import Any

import numpy as np

from greyfit.schemas.model import Model
from greyfit.solvers.screening.augment import fresh_name, replace_parameter, with_parameter
from greyfit.solvers.screening.candidate import Candidate, LibraryContext, fmt
from greyfit.solvers.screening.families.base import (
    NeedsTracedEquation,
    Scope,
    bind,
    declared_differences,
    param_regressor,
)
from greyfit.solvers.screening.families.time_varying import varying_parameters

THRESHOLDS = np.linspace(0.1, 0.9, 17)   # quantiles of |s| the switch is tried at


class StateDependent(NeedsTracedEquation):
    name = "state_dependent"
    scope: Scope = "parameter"
    generic = True

    def rewrite(self, model: Model, **spec: Any) -> tuple[Model, list[str]]:
        """`model` with p replaced by p + d·½(1 + tanh((|s| − thr)/(0.05·thr))), d a new parameter.

        Parameters
        ----------
        model : Model
            The model to rewrite (not changed: a copy is returned).
        **spec : Any
            `parameter`: p; `expr`: the switching variable s (model syntax); `label`: its name in the new
            parameter's; `threshold`: thr > 0.

        Returns
        -------
        tuple of (Model, list of str)
            The rewritten model and the new parameter's name.

        Raises
        ------
        ModelDefinitionError
            When a rewritten expression does not parse.
        """
        name, expr, label, thr = spec["parameter"], spec["expr"], spec["label"], spec["threshold"]
        d = fresh_name(model, f"d{name}_{label}")
        model = with_parameter(model, d, 0.0)
        # a switch smoothed over ±5 % of the threshold: a hard if_else makes the simulation
        # discontinuous in the state and the refit crawl
        width = fmt(0.05 * thr)
        return replace_parameter(
            model, name, f"({name} + {d}*0.5*(1 + tanh((abs({expr}) - {fmt(thr)})/{width})))"), [d]

    def candidates(self, ctx: LibraryContext) -> list[Candidate]:
        """Switches of every varying parameter in every switching variable, at the `THRESHOLDS` quantiles of |s|.

        Parameters
        ----------
        ctx : LibraryContext
            The model, the fitted trajectory and the discovery options.

        Returns
        -------
        list of Candidate
            One candidate per parameter, variable and positive threshold (generic).
        """
        out: list[Candidate] = []
        for name, j in varying_parameters(ctx):
            for expr, label, values, variables in switch_variables(ctx):
                out += self._thresholds(ctx, name, j, expr, label, values, variables)
        return out

    def _thresholds(self, ctx, name, j, expr, label, values, variables) -> list[Candidate]:
        out = []
        mags = np.abs(np.concatenate(values))
        for thr in np.unique(np.quantile(mags, THRESHOLDS)):
            if thr <= 0:
                continue
            reg = param_regressor(ctx.trace, j, [(np.abs(x) > thr).astype(float) for x in values])
            out.append(Candidate(self.name, reg, f"{name} -> {name} + d{name}_{label}*[|{expr}| > {fmt(thr)}]",
                                 f"{name} switches when |{expr}| exceeds {fmt(thr)}",
                                 bind(self, parameter=name, expr=expr, label=label, threshold=float(thr)),
                                 family=f"state_dependent:{name}:{label}", generic=True, modifies=name,
                                 variables=variables))
        return out


def switch_variables(ctx: LibraryContext) -> list[tuple[str, str, list[np.ndarray], tuple[str, ...]]]:
    """(expression, label, samples, variables): every state, and every declared difference of a state
    and an input (a relative speed).

    Parameters
    ----------
    ctx : LibraryContext
        The model and the fitted trajectory.

    Returns
    -------
    list of tuple
        (expression, label, samples per experiment, variables it is a function of), states first.
    """
    out: list[tuple[str, str, list[np.ndarray], tuple[str, ...]]] = [
        (s, s, ctx.state_values(s), (s,)) for s in ctx.states]
    inputs = set(ctx.trace.cm.inputs)
    seen: set[tuple[str, str]] = set()
    for _, a, b in declared_differences(ctx.model):
        if (a, b) in seen:
            continue
        seen.add((a, b))
        if (a in ctx.states and b in inputs) or (a in inputs and b in ctx.states):
            values = [x - y for x, y in zip(ctx.values(a), ctx.values(b))]
            out.append((f"{a} - {b}", f"{a}_{b}", values, (a, b)))
    return out
