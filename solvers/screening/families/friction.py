"""Coulomb friction: a force −Fc·sign(v) on a velocity that changes sign, smoothed as tanh(v/ε)."""
from __future__ import annotations

import numpy as np

from greyfit.solvers.screening.candidate import Candidate, LibraryContext, fmt
from greyfit.solvers.screening.families.base import TermFamily, changes_sign

WIDTHS = (0.001, 0.003, 0.01, 0.03)   # ε as fractions of the RMS of v: the refit chooses among them


class Coulomb(TermFamily):
    name = "coulomb"

    def candidates(self, ctx: LibraryContext) -> list[Candidate]:
        """A friction term −Fc_v·tanh(v/ε) (Fc_v ≥ 0) in the equation of every velocity that changes sign
        with substance (`base.changes_sign`).

        Parameters
        ----------
        ctx : LibraryContext
            The model, the fitted trajectory and the discovery options.

        Returns
        -------
        list of Candidate
            Per traced velocity, one candidate per width ε (`ctx.epsilon`, else `WIDTHS` times the RMS of
            v), marked for the refit to choose among them; a velocity that keeps its sign gets a note
            in `ctx.notes` instead.
        """
        out: list[Candidate] = []
        for v in ctx.velocities:
            vals = ctx.state_values(v)
            allv = np.concatenate(vals)
            if not changes_sign(vals):
                # on a quantity that keeps its sign (or dips a hair below 0 where its fit starts),
                # sign(v) is a constant: an offset, not friction
                ctx.notes.append(f"coulomb on {v} not tried: {v} does not change sign with substance "
                                 "(that would be an offset)")
                continue
            rms = float(np.sqrt(np.mean(allv ** 2))) or 1.0
            # the smoothing width matters: one far from the data's own leaves a misfit near v = 0
            # (stick-slip) that the loop would chase with spurious terms. The screening cannot tell
            # the widths apart (the smoothed derivative blurs the jump), so the refit chooses.
            for eps in ([ctx.epsilon] if ctx.epsilon else [f * rms for f in WIDTHS]):
                term = f"tanh({v}/{fmt(eps)})"
                c = self.term(ctx, v, [np.tanh(x / eps) for x in vals], term, f"Fc_{v}", "-", 0.0,
                              f"Coulomb friction on {v}: sign({v}) smoothed as {term}", -1.0, (v,),
                              stiffness=1.0 / eps, refit_variants=True, width=eps)
                if c is not None:
                    out.append(c)
        return out
