"""A hidden store: an unmeasured first-order storage that exchanges with a declared state.

A deep compartment in pharmacokinetics, a hidden thermal mass behind a node, an RC branch on a
circuit node, a second tank connected to the first: a new state z with τ·dz/dt = x − z, and a term
−k·(x − z) in the equation of the declared state x it exchanges with (k, τ > 0; in amounts,
A3' = k13·A1 − k31·A3 is this with z = A3·k31/k13, τ = 1/k31 and k = k13).

At k = 0 the store is decoupled: z is x low-passed with time constant τ (`low_pass`, from z = x at
the start: a store at rest with its node), and the candidate's column in x's equation is −(x − z)
per unit k, the part of x faster than τ with its sign turned. Unlike the lags (lags.py), whose
first-order effect is the same column for any small τ, a store is slow: its column depends on τ,
so the family proposes one candidate per point of a grid of τ spread over the record (`TAU_GRID`,
fractions of the record's length), each counted as a try (the screen's Bonferroni covers the grid).
A slow store's misfit is smooth and is what an AR noise model absorbs: the generic tests of the
residual do not see it, a column of this shape does.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from greyfit.schemas.model import Model
from greyfit.solvers.screening.augment import add_term, fresh_name, with_parameter
from greyfit.solvers.screening.candidate import Candidate, LibraryContext, Regressor, fmt
from greyfit.solvers.screening.families.base import NeedsTracedEquation, Scope, bind

# τ as a fraction of the record's length: from a few percent (a store that fills within the
# record) to the whole record (one that is still filling at its end); geometric, 4 points
TAU_GRID = (1 / 27, 1 / 9, 1 / 3, 1.0)


def low_pass(x: np.ndarray, t: np.ndarray, tau: float) -> np.ndarray:
    """z with τ·dz/dt = x − z, z(t_0) = x(t_0), for x linear between its samples (exact).

    Parameters
    ----------
    x : numpy.ndarray
        The samples, (n,).
    t : numpy.ndarray
        Their times, (n,), increasing.
    tau : float
        The time constant (> 0).

    Returns
    -------
    numpy.ndarray
        (n,) z at the samples.
    """
    z = np.empty_like(x, dtype=float)
    if x.size == 0:
        return z
    z[0] = x[0]
    for k in range(x.size - 1):
        h = t[k + 1] - t[k]
        a = np.exp(-h / tau)
        s = (x[k + 1] - x[k]) / h if h > 0 else 0.0
        z[k + 1] = x[k + 1] - s * tau + (z[k] - x[k] + s * tau) * a
    return z


def add_store(model: Model, state: str, tau: float) -> tuple[Model, list[str]]:
    """`model` with a store z of `state`: τ·dz/dt = state − z, and −k·(state − z) in d(state)/dt.

    Parameters
    ----------
    model : Model
        The model (not changed: a copy is returned).
    state : str
        The declared state the store exchanges with.
    tau : float
        τ's start (a free parameter, bounded below by a hundredth of it); k starts at 1e-6, bounded
        below by 0.

    Returns
    -------
    tuple of (Model, list of str)
        The augmented model and the new parameters' names (k, τ).
    """
    z = fresh_name(model, f"{state}_store")
    with_z = model.model_copy(update={"states": [*model.states, z]})
    tau_name = fresh_name(with_z, f"{z}_tau")
    model = with_parameter(model, tau_name, float(tau), lower=float(tau) / 100)
    k_name = fresh_name(model.model_copy(update={"states": [*model.states, z]}), f"{z}_k")
    model = with_parameter(model, k_name, 1e-6, lower=0.0)
    outputs = model.measured_outputs()   # written out: the new state is not measured
    equations = {**model.equations, z: f"({state} - {z}) / {tau_name}"}
    model = model.model_copy(update={"states": [*model.states, z], "equations": equations, "outputs": outputs})
    return add_term(model, state, f"{k_name}*({state} - {z})", "-"), [k_name, tau_name]


class HiddenStore(NeedsTracedEquation):
    """A declared state exchanges with an unmeasured first-order store (a deep compartment, a hidden
    thermal mass, an RC branch, a second tank)."""

    name = "hidden_store"
    scope: Scope = "equation"
    generic = True

    def rewrite(self, model: Model, **spec: Any) -> tuple[Model, list[str]]:
        """`model` with a store of `spec['state']` (`add_store`).

        Parameters
        ----------
        model : Model
            The model to rewrite (not changed: a copy is returned).
        **spec : Any
            `state`: the declared state; `tau`: the store's time constant's start.

        Returns
        -------
        tuple of (Model, list of str)
            The rewritten model and the new parameters' names.
        """
        return add_store(model, spec["state"], spec["tau"])

    def candidates(self, ctx: LibraryContext) -> list[Candidate]:
        """A store of every traced state that is not a position (dx/dt = v), one per τ of `TAU_GRID`
        (fractions of the longest record), its column −(x − z_τ) in the state's own equation.

        Parameters
        ----------
        ctx : LibraryContext
            The model and the fitted trajectory.

        Returns
        -------
        list of Candidate
            Up to len(`TAU_GRID`) candidates per state.
        """
        span = max((float(t[-1] - t[0]) for t in ctx.trace.t if t.size > 1), default=0.0)
        if span <= 0:
            return []
        out = []
        for s in ctx.force_equations():
            i = ctx.states.index(s)
            values = ctx.state_values(s)
            for frac in TAU_GRID:
                tau = frac * span
                cols = [-(x - low_pass(x, t, tau)) for x, t in zip(values, ctx.trace.t)]
                if not all(np.all(np.isfinite(c)) for c in cols) or not any(np.any(c != 0) for c in cols):
                    continue
                reg: Regressor = {i: cols}
                out.append(Candidate(self.name, reg, f"- k*({s} - z), tau*dz/dt = {s} - z (tau ~ {fmt(tau)})",
                                     f"{s} exchanges with a hidden first-order store (a deep compartment, a "
                                     f"hidden mass or capacity) of time constant about {fmt(tau)}",
                                     bind(self, state=s, tau=tau), sign=1.0, family=f"hidden_store:{s}",
                                     variables=(s,), generic=self.generic))
        return out


__all__ = ["HiddenStore", "add_store", "low_pass", "TAU_GRID"]
