"""Radiative exchange across a declared temperature difference: T − Ta in the model gets a companion
s·(T⁴ − Ta⁴) (Stefan-Boltzmann), with the sign of the declared linear exchange.

The term is written in units of a reference R (the RMS of T) so that its coefficient is of the size of
the linear one: s·(T⁴ − Ta⁴) = σ·((T/R)⁴ − (Ta/R)⁴) with σ = s·R⁴.
"""
from __future__ import annotations

import numpy as np

from greyfit.solvers.screening.candidate import Candidate, LibraryContext, fmt
from greyfit.solvers.screening.families.base import TermFamily, declared_differences


class Radiation(TermFamily):
    name = "radiation"

    def candidates(self, ctx: LibraryContext) -> list[Candidate]:
        """A radiative term σ·((a/R)⁴ − (b/R)⁴) for every declared difference a − b of a state in a traced equation.

        Parameters
        ----------
        ctx : LibraryContext
            The model, the fitted trajectory and the discovery options.

        Returns
        -------
        list of Candidate
            One candidate per difference whose samples stay positive and whose equation depends on a
            (with the sign of that dependence).
        """
        out: list[Candidate] = []
        for eq, a, b in declared_differences(ctx.model):
            if a not in ctx.states or eq not in ctx.states or not ctx.traced(eq):
                continue
            va, vb = ctx.values(a), ctx.values(b)
            both = np.concatenate(va + vb)
            if np.mean(both > 0) < 0.999:
                continue   # T⁴ is a law of absolute temperatures, which stay positive
            slope = float(np.mean(np.concatenate([j[:, ctx.states.index(eq), ctx.states.index(a)]
                                                  for j in ctx.trace.jx])))
            if slope == 0:
                continue
            r = float(np.sqrt(np.mean(np.concatenate(va) ** 2)))
            term = f"(({a}/{fmt(r)})^4 - ({b}/{fmt(r)})^4)"
            values = [(x / r) ** 4 - (y / r) ** 4 for x, y in zip(va, vb)]
            # exchange in the direction of the declared linear one: a loss where ∂f/∂a < 0
            sign, phys = ("-", -1.0) if slope < 0 else ("+", 1.0)
            c = self.term(ctx, eq, values, term, f"sigma_{a}", sign, 0.0,
                          f"a fourth-power exchange s*({a}^4 - {b}^4) in d{eq}/dt (s = sigma_{a}/{fmt(r)}^4; "
                          f"radiation where {a} is an absolute temperature)", phys,
                          (a, b) if b in ctx.states else (a,))
            if c is not None:
                c.family = f"{self.name}:{eq}:{a}:{b}"
                out.append(c)
        return out
