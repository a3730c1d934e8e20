"""What a family of effects is: the `Family` protocol, and the helpers most families build terms with.

A family says what it supports (`scope`, `generic`, `supports`), generates its candidates from the
fitted trajectory (`candidates`), and rewrites a model with one of them (`rewrite`, bound into each
candidate's `apply`). The loop calls them in that order: supports → candidates → (screen) → apply.
"""
from __future__ import annotations

from functools import partial
from typing import Any, Literal, Protocol, runtime_checkable

import numpy as np

from greyfit.schemas.model import Model
from greyfit.solvers.discovery.augment import add_term, fresh_name, with_parameter
from greyfit.solvers.discovery.candidate import Candidate, LibraryContext, Regressor

# where a family's terms enter: a term in a state equation, a law of a declared parameter, a
# change of an input, or the output path (the sensor)
Scope = Literal["equation", "parameter", "input", "output"]


@runtime_checkable
class Family(Protocol):
    """One family of effects in the library (one module under `families/`, one line in the registry).

    Attributes
    ----------
    name : str
        The effect's name in `DiscoveryOptions.effects` (schemas/discovery.py checks it is listed).
    scope : Scope
        Where its terms enter the model.
    generic : bool
        A catch-all shape (a switching coefficient, a change in time, a delay) rather than a named
        physical law: kept only where no named law explains as much (`discriminate`).
    """

    name: str
    scope: Scope
    generic: bool

    def supports(self, ctx: LibraryContext) -> bool:
        """Whether the family can propose anything on this trace (e.g. the output path needs outputs)."""
        ...

    def candidates(self, ctx: LibraryContext) -> list[Candidate]:
        """Its candidate terms on this trace, each with its regressor; notes go to `ctx.notes`."""
        ...

    def rewrite(self, model: Model, **spec: Any) -> tuple[Model, list[str]]:
        """`model` with the candidate described by `spec`, and the new parameters' names."""
        ...


def bind(family: "Family | TermFamily", **spec: Any):
    """A candidate's `apply`: the family's rewrite with the candidate's own spec."""
    return partial(family.rewrite, **spec)


def add_parameter_term(model: Model, *, equation: str, term: str, stem: str, sign: str,
                       lower: float | None) -> tuple[Model, list[str]]:
    """`sign p*term` added to d(equation)/dt with a new parameter p (start 0, or 1e-6 at a bound of 0)."""
    name = fresh_name(model, stem)
    model = with_parameter(model, name, 0.0 if lower is None else 1e-6, lower=lower)
    return add_term(model, equation, f"{name}*{term}", sign), [name]


class TermFamily:
    """A family whose candidates are one term `sign p*term` in one state equation (subclasses
    provide `candidates`)."""

    name = ""
    scope: Scope = "equation"
    generic = False

    def supports(self, ctx: LibraryContext) -> bool:
        return bool(ctx.trace.traced)

    def rewrite(self, model: Model, **spec: Any) -> tuple[Model, list[str]]:
        return add_parameter_term(model, **spec)

    def term(self, ctx: LibraryContext, eq_state: str, regressor: list[np.ndarray], term: str, stem: str,
             sign: str, lower: float | None, description: str, phys_sign: float,
             variables: tuple[str, ...] = (), **extra: Any) -> Candidate | None:
        """The candidate `sign stem*term` in d(eq_state)/dt; None where that equation is not traced.

        A '-' term with a positive parameter contributes -g: the regression coefficient is on +g,
        so `phys_sign` is the sign the coefficient of +g must have."""
        if not ctx.traced(eq_state):
            return None
        eq = ctx.states.index(eq_state)
        regs: Regressor = {eq: regressor}
        return Candidate(self.name, regs, f"{sign} {stem}*{term}", description,
                         bind(self, equation=eq_state, term=term, stem=stem, sign=sign, lower=lower),
                         sign=phys_sign, family=f"{self.name}:{eq_state}", generic=self.generic,
                         variables=variables, **extra)


def sensitivity_regressor(trace, jacobians: list[np.ndarray], j: int, change: list[np.ndarray]) -> Regressor:
    """∂f_i/∂z_j · change(t) for every traced equation that depends on z_j (a parameter or input)."""
    reg = {}
    for i in trace.traced:
        cols = [jac[:, i, j] * c for jac, c in zip(jacobians, change)]
        if any(np.any(c != 0) for c in cols):
            reg[i] = cols
    return reg


def param_regressor(trace, j: int, shape: list[np.ndarray]) -> Regressor:
    """The column of a parameter θ_j that varies as θ_j + β·shape(t): ∂f/∂θ_j · shape."""
    return sensitivity_regressor(trace, trace.jp, j, shape)


def shared_free(model: Model) -> list[str]:
    """Declared parameters a law in a state or in time can act on (free, one value for all records)."""
    return [p.name for p in model.parameters if not p.fixed and not p.per_experiment]


def declared_differences(model: Model) -> list[tuple[str, str, str]]:
    """(equation, a, b) for every difference `a - b` of two names the model's equations and
    definitions use: a relative speed v4 - wd, a temperature difference T - Ta. Laws of such a
    difference (radiation T⁴ − Ta⁴, a damper that switches with |v4 − wd|) act on it."""
    from greyfit.solvers.model.expressions import parse
    found: list[tuple[str, str, str]] = []
    texts = [(s, model.equations[s]) for s in model.states] + list(model.definitions.items())
    for eq, text in texts:
        stack = [parse(text, f"equations.{eq}")]
        while stack:
            node = stack.pop()
            if node[0] == "bin" and node[1] == "-" and node[2][0] == "name" and node[3][0] == "name":
                pair = (eq, node[2][1], node[3][1])
                if pair not in found:
                    found.append(pair)
            if node[0] in ("bin", "cmp"):
                stack += [node[2], node[3]]
            elif node[0] == "neg":
                stack.append(node[1])
            elif node[0] == "call":
                stack += list(node[2])
    return found


def physical_variables(ctx: LibraryContext) -> set[str]:
    """Names whose samples a law may be a function of: states, inputs, constants."""
    return set(ctx.states) | set(ctx.trace.cm.inputs) | set(ctx.model.constants)
