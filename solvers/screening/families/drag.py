"""Quadratic (turbulent) drag: a force −Cd·v|v| on a velocity."""
from __future__ import annotations

import numpy as np

from greyfit.solvers.screening.candidate import Candidate, LibraryContext
from greyfit.solvers.screening.families.base import TermFamily


class QuadraticDrag(TermFamily):
    name = "quadratic_drag"

    def candidates(self, ctx: LibraryContext) -> list[Candidate]:
        """A drag term −Cd_v·v|v| (Cd_v ≥ 0) in the equation of every velocity.

        Parameters
        ----------
        ctx : LibraryContext
            The model, the fitted trajectory and the discovery options.

        Returns
        -------
        list of Candidate
            One candidate per traced velocity equation.
        """
        out = [self.term(ctx, v, [x * np.abs(x) for x in ctx.state_values(v)], f"{v}*abs({v})", f"Cd_{v}",
                         "-", 0.0, f"quadratic drag on {v}", -1.0, (v,)) for v in ctx.velocities]
        return [c for c in out if c is not None]
