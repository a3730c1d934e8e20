"""Cubic (hardening or softening) stiffness: a force −k3·x³ on the velocity of a position."""
from __future__ import annotations

from greyfit.solvers.screening.candidate import Candidate, LibraryContext
from greyfit.solvers.screening.families.base import TermFamily


class CubicStiffness(TermFamily):
    name = "cubic_stiffness"

    def candidates(self, ctx: LibraryContext) -> list[Candidate]:
        """A term −k3_x·x³ (any sign) in the equation of the velocity of every position x.

        Parameters
        ----------
        ctx : LibraryContext
            The model, the fitted trajectory and the discovery options.

        Returns
        -------
        list of Candidate
            One candidate per position whose velocity equation is traced.
        """
        out = [self.term(ctx, v, [x ** 3 for x in ctx.state_values(x_name)], f"{x_name}^3", f"k3_{x_name}", "-",
                         None, f"cubic (hardening or softening) stiffness on {x_name}", 0.0, (x_name,))
               for v, x_name in ctx.pos_of.items()]
        return [c for c in out if c is not None]
