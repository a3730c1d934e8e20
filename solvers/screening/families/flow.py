"""A square-root law: every flow the model computes from a positive state follows its square root
(Torricelli outflow where the state is a level); or an orifice outflow −k·√s beside the declared
flows of s (a leak, a second outlet), a term of its own with a new coefficient k ≥ 0.

Over a narrow range of levels √s is nearly affine in s, so the term beside the declared flows is
nearly a constant source plus a change of the declared outflow coefficient: the two are refitted
beside each other (their screening columns are the same on such data) and the refit's BIC decides,
or says `ambiguous`."""
from __future__ import annotations

from typing import Any

import numpy as np

from greyfit.schemas.model import Model
from greyfit.solvers.screening.augment import replace_in_equations
from greyfit.solvers.screening.candidate import Candidate, LibraryContext, fmt
from greyfit.solvers.screening.families.base import (
    NeedsTracedEquation,
    Scope,
    add_parameter_term,
    bind,
    sensitivity_regressor,
)


class SqrtFlow(NeedsTracedEquation):
    """The declared flows through s (say k1*h1, out of tank 1 and into tank 2) change law together,
    so mass stays conserved: s -> sqrt(max(s, 0)) in the equations. Scored as the family
    s -> s + β (sqrt(s) − s): forcing ∂f/∂s · (sqrt(s) − s); the flow coefficients absorb the
    linear part, so the score does not depend on the units of s."""

    name = "sqrt_flow"
    scope: Scope = "equation"
    generic = False

    def rewrite(self, model: Model, **spec: Any) -> tuple[Model, list[str]]:
        """`model` with state s replaced by sqrt(max(s, floor)) in its equations and definitions.

        Parameters
        ----------
        model : Model
            The model to rewrite (the outputs keep measuring s itself).
        **spec : Any
            `state`: the level s; `floor`: the small positive floor, as text.

        Returns
        -------
        tuple of (Model, list of str)
            The rewritten model and no new parameters; for the outflow beside the declared flows
            (`spec` of `add_parameter_term`), the model with the term and its new coefficient.
        """
        if "term" in spec:
            return add_parameter_term(model, **spec)
        s, floor = spec["state"], spec["floor"]
        return replace_in_equations(model, s, f"sqrt(max({s}, {floor}))"), []

    def candidates(self, ctx: LibraryContext) -> list[Candidate]:
        """The change of law s -> sqrt(s) for every positive, non-mechanical state that flows depend on.

        Parameters
        ----------
        ctx : LibraryContext
            The model, the fitted trajectory and the discovery options.

        Returns
        -------
        list of Candidate
            Per such state (at least 90 % of its samples positive, not a position or velocity), the change
            of law and, where its own equation has a declared flow through it, an outflow −k·√s beside it.
        """
        out = [c for s in ctx.states for c in (self._one(ctx, s), self._beside(ctx, s))]
        return [c for c in out if c is not None]

    def _beside(self, ctx: LibraryContext, s: str) -> Candidate | None:
        """−k·sqrt(s) in ds/dt, k ≥ 0, where ds/dt declares a flow through s (∂f_s/∂s ≠ 0 on the trace)."""
        trace = ctx.trace
        k = ctx.states.index(s)
        if s in ctx.pos_of or s in ctx.vel_of or not ctx.traced(s):
            return None
        allv = np.concatenate([x[k] for x in trace.x])
        if np.mean(allv > 0) < 0.9 or not any(np.any(jx[:, k, k] != 0) for jx in trace.jx):
            return None
        floor = fmt(1e-6 * float(np.sqrt(np.mean(allv ** 2))))
        term = f"sqrt(max({s}, {floor}))"
        stem = f"k_sqrt_{s}"
        return Candidate(self.name, {k: [np.sqrt(np.maximum(x[k], 0)) for x in trace.x]}, f"- {stem}*{term}",
                         f"an orifice outflow beside the declared flows of {s}: -k*sqrt({s}) in d{s}/dt",
                         bind(self, equation=s, term=term, stem=stem, sign="-", lower=0.0), sign=-1.0,
                         family=f"sqrt_flow_beside:{s}", variables=(s,))

    def _one(self, ctx: LibraryContext, s: str) -> Candidate | None:
        trace = ctx.trace
        k = ctx.states.index(s)
        allv = np.concatenate([x[k] for x in trace.x])
        if s in ctx.pos_of or s in ctx.vel_of or np.mean(allv > 0) < 0.9:
            return None   # a square-root law of a quantity that stays positive: not a position or a velocity
        change = [np.sqrt(np.maximum(x[k], 0)) - x[k] for x in trace.x]
        reg = sensitivity_regressor(trace, trace.jx, k, change)
        if not reg:
            return None
        flows_into = sorted(ctx.states[i] for i in reg if ctx.states[i] != s)
        # a floor far below the levels seen keeps sqrt's slope finite where a level starts at 0
        floor = fmt(1e-6 * float(np.sqrt(np.mean(allv ** 2))))
        where = f"d{s}/dt" + "".join(f", d{o}/dt" for o in flows_into)
        return Candidate(self.name, reg, f"{s} -> sqrt(max({s}, 0)) in the flows of {where}",
                         f"a square-root law: the flows through {s} follow sqrt({s}), not {s}",
                         bind(self, state=s, floor=floor), sign=1.0, family=f"sqrt_flow:{s}", variables=(s,))
