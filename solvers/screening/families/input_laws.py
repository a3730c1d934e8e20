"""Nonlinear laws of an input in a state equation: its powers u², u·|u|, and its products u·x with the
states the equation involves.

A lamp's power grows as the voltage squared, a propeller's thrust as u·|u|, an energy flow as the
mass flow times a temperature; a model that takes the input linearly can only approximate them.
Every term is its own hypothesis (any sign, a new parameter from 0).
"""
from __future__ import annotations

import numpy as np

from greyfit.solvers.screening.candidate import Candidate, LibraryContext
from greyfit.solvers.screening.families.base import TermFamily

POWERS = (("{u}^2", "2", lambda u: u * u), ("{u}*abs({u})", "abs", lambda u: u * np.abs(u)))


class InputLaw(TermFamily):
    name = "input_law"

    def candidates(self, ctx: LibraryContext) -> list[Candidate]:
        """u², u·|u| and u·x for every input u (and state x) a traced force equation depends on.

        Parameters
        ----------
        ctx : LibraryContext
            The model, the fitted trajectory and the discovery options.

        Returns
        -------
        list of Candidate
            One candidate per term and equation, each its own family.
        """
        out: list[Candidate] = []
        for eq in ctx.force_equations():
            involved = ctx.equation_variables(eq)
            states = [s for s in involved if s in ctx.states]
            for u in [v for v in involved if v in ctx.trace.cm.inputs]:
                for term, label, values, variables in self._terms(ctx, u, states):
                    c = self.term(ctx, eq, values, term, f"c_{u}{label}_{eq}", "+", None,
                                  f"a nonlinear law of the input: {term} in d{eq}/dt", 0.0, variables)
                    if c is not None:
                        c.family = f"{self.name}:{eq}:{term}"
                        out.append(c)
        return out

    @staticmethod
    def _terms(ctx: LibraryContext, u: str, states: list[str]):
        vu = ctx.input_values(u)
        for text, label, fn in POWERS:
            yield text.format(u=u), label, [fn(x) for x in vu], (u,)
        for x in states:
            yield f"{u}*{x}", f"_{x}", [a * b for a, b in zip(vu, ctx.state_values(x))], (u, x)
