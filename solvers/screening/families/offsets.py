"""A constant offset in a state equation (a source, a bias force), not in a kinematic identity."""
from __future__ import annotations

import numpy as np

from greyfit.solvers.screening.candidate import Candidate, LibraryContext
from greyfit.solvers.screening.families.base import TermFamily


class Offset(TermFamily):
    name = "offset"

    def candidates(self, ctx: LibraryContext) -> list[Candidate]:
        """A constant term +f0_s (any sign) in every traced equation that is not a kinematic identity.

        Parameters
        ----------
        ctx : LibraryContext
            The model, the fitted trajectory and the discovery options.

        Returns
        -------
        list of Candidate
            One candidate per such equation.
        """
        out = [self.term(ctx, s, [np.ones_like(t) for t in ctx.trace.t], "1", f"f0_{s}", "+", None,
                         f"constant offset in d{s}/dt", 0.0) for s in ctx.force_equations()]
        return [c for c in out if c is not None]
