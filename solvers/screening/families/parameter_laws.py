"""A declared parameter that depends smoothly on a state or an input: a linear or quadratic law
p(x) = p + a·(x − x₀) [or + b·(x − x₀)²], and the Arrhenius law p(T) = p·exp(−(E/R)(1/T − 1/T₀)).

x₀ is 0 for a variable that changes sign (an even law of a position stays even) and its mean
otherwise (p keeps its meaning: the value at the typical operating point). The Arrhenius exponent
is written as Ê·(T₀/T − 1) with Ê = E/(R·T₀), so its coefficient is O(1) for the solver.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from greyfit.schemas.model import Model
from greyfit.solvers.screening.augment import fresh_name, replace_parameter, with_parameter
from greyfit.solvers.screening.candidate import Candidate, LibraryContext, fmt
from greyfit.solvers.screening.families.base import NeedsTracedEquation, Scope, bind, param_regressor
from greyfit.solvers.screening.families.time_varying import varying_parameters

# an absolute temperature in a process rarely doubles over a record (300 -> 600 K); a variable that
# does (a level, a flow, a temperature in °C) is not one Arrhenius' law is written in
ABSOLUTE_SPAN = 2.0


def _law_variables(ctx: LibraryContext, j: int) -> list[tuple[str, list[np.ndarray]]]:
    """Every state and input, with their samples: a parameter's dependence on a variable its equation
    does not involve (a rate constant on the temperature) is exactly the coupling a model may lack."""
    return [(s, ctx.state_values(s)) for s in ctx.states] + [(u, ctx.input_values(u)) for u in ctx.trace.cm.inputs]


class ParameterLaw(NeedsTracedEquation):
    name = "parameter_law"
    scope: Scope = "parameter"
    generic = False
    POWERS = ((1, "linear"), (2, "quadratic"))

    def rewrite(self, model: Model, **spec: Any) -> tuple[Model, list[str]]:
        """`model` with parameter p replaced by p + d·(x − x₀)^power, d a new parameter.

        Parameters
        ----------
        model : Model
            The model to rewrite (not changed: a copy is returned).
        **spec : Any
            `parameter`: p; `variable`: x; `reference`: x₀ (0: x itself); `power`: 1 or 2.

        Returns
        -------
        tuple of (Model, list of str)
            The rewritten model and the new parameter's name.

        Raises
        ------
        ModelDefinitionError
            When a rewritten expression does not parse.
        """
        name, var, ref, power = spec["parameter"], spec["variable"], spec["reference"], spec["power"]
        d = fresh_name(model, f"{name}_{var}{power}")
        model = with_parameter(model, d, 0.0)
        shifted = var if ref == 0 else f"({var} - {fmt(ref)})"
        law = shifted if power == 1 else f"{shifted}^{power}"
        return replace_parameter(model, name, f"({name} + {d}*{law})"), [d]

    def candidates(self, ctx: LibraryContext) -> list[Candidate]:
        """Linear and quadratic laws of every varying parameter in every state and input.

        Parameters
        ----------
        ctx : LibraryContext
            The model, the fitted trajectory and the discovery options.

        Returns
        -------
        list of Candidate
            Per parameter, variable that varies, and power (1, 2), one candidate (marked approximating).
        """
        out: list[Candidate] = []
        for name, j in varying_parameters(ctx):
            for var, values in _law_variables(ctx, j):
                allv = np.concatenate(values)
                if np.ptp(allv) <= 0:
                    continue
                ref = 0.0 if min(np.mean(allv > 0), np.mean(allv < 0)) > 0.02 else float(np.mean(allv))
                for power, kind in self.POWERS:
                    reg = param_regressor(ctx.trace, j, [(x - ref) ** power for x in values])
                    shown = var if ref == 0 else f"({var} - {fmt(ref)})"
                    out.append(Candidate(
                        self.name, reg,
                        f"{name} -> {name} + {name}_{var}{power}*{shown}" + ("^2" if power == 2 else ""),
                        f"{name} depends on {var} ({kind} law)",
                        bind(self, parameter=name, variable=var, reference=ref, power=power),
                        family=f"{self.name}:{name}:{var}:{power}", modifies=name,
                        variables=(var,), approximating=True))
        return out


class Arrhenius(NeedsTracedEquation):
    name = "arrhenius"
    scope: Scope = "parameter"
    generic = False

    def rewrite(self, model: Model, **spec: Any) -> tuple[Model, list[str]]:
        """`model` with parameter p replaced by p·exp(Ê·(1 − T₀/T)), Ê a new parameter.

        Parameters
        ----------
        model : Model
            The model to rewrite (not changed: a copy is returned).
        **spec : Any
            `parameter`: p; `variable`: T; `reference`: T₀.

        Returns
        -------
        tuple of (Model, list of str)
            The rewritten model and the new parameter's name.

        Raises
        ------
        ModelDefinitionError
            When a rewritten expression does not parse.
        """
        name, var, ref = spec["parameter"], spec["variable"], spec["reference"]
        e = fresh_name(model, f"E_{name}_{var}")
        model = with_parameter(model, e, 0.0)
        return replace_parameter(model, name, f"({name}*exp({e}*(1 - {fmt(ref)}/{var})))"), [e]

    def candidates(self, ctx: LibraryContext) -> list[Candidate]:
        """An Arrhenius law of every varying parameter in every variable that can be an absolute temperature.

        Parameters
        ----------
        ctx : LibraryContext
            The model, the fitted trajectory and the discovery options.

        Returns
        -------
        list of Candidate
            Per parameter and variable that is positive, varies and stays within a factor `ABSOLUTE_SPAN`,
            one candidate (reference T₀ the variable's mean).
        """
        out: list[Candidate] = []
        for name, j in varying_parameters(ctx):
            value = float(ctx.trace.p[0][ctx.trace.cm.parameters.index(name)])
            for var, values in _law_variables(ctx, j):
                allv = np.concatenate(values)
                lo, hi = float(np.min(allv)), float(np.max(allv))
                if lo <= 0 or hi > ABSOLUTE_SPAN * lo or hi - lo <= 1e-3 * float(np.mean(allv)):
                    continue   # a law of an absolute temperature: positive, varying, within a factor 2
                ref = float(np.mean(allv))
                # d/dÊ of p·exp(Ê(1 − T₀/T)) at Ê = 0: p·(1 − T₀/T)
                reg = param_regressor(ctx.trace, j, [value * (1 - ref / x) for x in values])
                out.append(Candidate(
                    self.name, reg, f"{name} -> {name}*exp(E_{name}_{var}*(1 - {fmt(ref)}/{var}))",
                    f"{name} follows an Arrhenius law of {var}: {name}*exp(-E/R*(1/{var} - 1/{fmt(ref)})), "
                    f"E/R = E_{name}_{var}*{fmt(ref)}",
                    bind(self, parameter=name, variable=var, reference=ref),
                    family=f"{self.name}:{name}:{var}", modifies=name, variables=(var,)))
        return out
