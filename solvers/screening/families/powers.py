"""Powers and products of up to two states in a state equation: x², x|x|, x³, x·v, x²·v, x·|v|, …,
and the odd powers of a declared difference, (a − b)|a − b| and (a − b)³.

These are the laws of real plants the named families do not cover: a damping that grows with the
amplitude (μx²v, Van der Pol), a spring-damper product, a turbulent exchange across a difference.
Every term is its own hypothesis and counts in the Bonferroni level; a term some named family
already proposes (v|v| as quadratic drag, x³ as a cubic spring) is left to it (`effects.library`
drops the later of two identical columns).
"""
from __future__ import annotations

import re
from itertools import combinations

import numpy as np

from greyfit.solvers.screening.candidate import Candidate, LibraryContext
from greyfit.solvers.screening.families.base import TermFamily, declared_differences

# (text, function) of the single-variable powers and the two-variable products, degree 2 and 3
SINGLE = (("{a}^2", lambda a: a * a), ("{a}*abs({a})", lambda a: a * np.abs(a)), ("{a}^3", lambda a: a ** 3))
PAIR = (("{a}*{b}", lambda a, b: a * b), ("{a}^2*{b}", lambda a, b: a * a * b), ("{a}*{b}^2", lambda a, b: a * b * b),
        ("{a}*abs({b})", lambda a, b: a * np.abs(b)), ("abs({a})*{b}", lambda a, b: np.abs(a) * b))
DIFFERENCE = (("({a} - {b})*abs({a} - {b})", lambda d: d * np.abs(d)), ("({a} - {b})^3", lambda d: d ** 3))


def _stem(term: str, eq: str) -> str:
    """A parameter name from the term: x^2*v in dv/dt -> c_x2_v_v."""
    core = re.sub(r"abs\((\w+)\)", r"abs\1", term).replace("^", "")
    return "c_" + re.sub(r"[^A-Za-z0-9]+", "_", core).strip("_") + f"_{eq}"


class PowerLaw(TermFamily):
    name = "power_law"

    def candidates(self, ctx: LibraryContext) -> list[Candidate]:
        """Every power or product of degree 2 or 3 of the states in each force equation (any sign).

        Parameters
        ----------
        ctx : LibraryContext
            The model, the fitted trajectory and the discovery options.

        Returns
        -------
        list of Candidate
            One candidate per term and equation (`SINGLE`, `PAIR` of the states the equation involves, and
            `DIFFERENCE` of its declared differences), each its own family and marked approximating.
        """
        out: list[Candidate] = []
        for eq in ctx.force_equations():
            for term, values, variables in self._terms(ctx, eq):
                c = self.term(ctx, eq, values, term, _stem(term, eq), "+", None,
                              f"a power law {term} in d{eq}/dt", 0.0, variables)
                if c is not None:
                    c.family = f"{self.name}:{eq}:{term}"   # each term its own hypothesis, refitted apart
                    c.approximating = True
                    out.append(c)
        return out

    def _terms(self, ctx: LibraryContext, eq: str):
        states = [s for s in ctx.equation_variables(eq) if s in ctx.states]
        for a in states:
            va = ctx.state_values(a)
            for text, fn in SINGLE:
                yield text.format(a=a), [fn(x) for x in va], (a,)
        for a, b in combinations(states, 2):
            va, vb = ctx.state_values(a), ctx.state_values(b)
            for text, pair in PAIR:
                yield text.format(a=a, b=b), [pair(x, y) for x, y in zip(va, vb)], (a, b)
        for where, a, b in declared_differences(ctx.model):
            if where != eq or a == b:
                continue
            diff = [x - y for x, y in zip(ctx.values(a), ctx.values(b))]
            for text, law in DIFFERENCE:
                yield text.format(a=a, b=b), [law(d) for d in diff], tuple(v for v in (a, b) if v in states)
