"""Candidates scored against the learned shape of the missing term (`shape`, `shape_relate`).

The shape step estimates, without assuming a form, the disturbance d̂ that the current fit leaves on
each equation and output path, and how much of it a smooth function of one variable explains (the
share S of its most likely channel). Two tests use it:

- **A law without the shape approximates** (`shape_note`). A candidate law g enters one equation
  (or output path); `shape_relate.shape_agreement` says how much of that channel's d̂ it explains
  (with the terms linear in the states and inputs the declared parameters take up). A law that
  explains `SHAPE_DISAGREEMENT` less than the free smooth function does not have the shape of what is
  missing: added, it is labelled "approximates; not identified". Constant terms (an offset) have no
  shape to compare and are not judged so.
- **Memory is not named** (`memory_objection`). When the most likely disturbance holds most of the
  residual (`MEMORY_HOLDS`) and no smooth function of one present variable explains it
  (S < `MEMORY_SHARE`: it depends on the history, as a hysteresis does), a law of the present
  variables is a stand-in unless it explains most of what is left: a refit that leaves the residual
  above `leftover.UNEXPLAINED_RATIO` times the noise and removes less than `MIN_EXCESS_SHARE` of the
  residual's excess over the noise is refused (reason `shape`); the result then says `unexplained`,
  with the shape. Coloured measurement noise (`leftover.looks_like_coloured_noise`) is no such memory.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from greyfit.schemas.discovery import RejectedCandidate
from greyfit.schemas.fit import FitResult
from greyfit.solvers.discovery.confirm import LoopState, Refitted
from greyfit.solvers.discovery.leftover import UNEXPLAINED_RATIO, looks_like_coloured_noise
from greyfit.solvers.discovery.parsimony import rejected
from greyfit.solvers.discovery.shape import ShapeResult
from greyfit.solvers.discovery.shape_relate import ShapeEstimate, relate, shape_agreement
from greyfit.solvers.screening.candidate import Candidate
from greyfit.solvers.screening.screening import Screening

SHAPE_DISAGREEMENT = 0.2   # a law explaining this much less of d̂ than a free smooth function does not have its shape
MEMORY_SHARE = 0.6         # d̂ explained less than this by any smooth function of one variable: it has memory
MEMORY_HOLDS = 0.5         # ... where that disturbance holds at least this share of the residual
MIN_EXCESS_SHARE = 0.5     # there, a law must remove this share of the residual's excess over the noise


@dataclass
class ShapeFit:
    """How a candidate law agrees with the learned disturbance of the channel it enters."""

    channel: str                 # the state whose equation it enters, or "output y"
    agreement: float             # share of d̂ explained by the law (with the linear terms)
    share: float | None          # share of d̂ a smooth function of `variable` explains
    variable: str | None


def channel_of(shape: ShapeResult, cand: Candidate, states: list[str], outputs: list[str]
               ) -> tuple[ShapeEstimate, list[np.ndarray]] | None:
    """The learned disturbance of the one channel a candidate enters, and the candidate's term there.

    Parameters
    ----------
    shape : ShapeResult
        The shape learned at the fit the candidate was screened at.
    cand : Candidate
        The candidate (its regressor per equation index, or per output index).
    states, outputs : list of str
        The names of the equation and output indices (`Screening.states`, `Screening.outputs`).

    Returns
    -------
    tuple of (ShapeEstimate, list of numpy.ndarray) or None
        The channel's estimate and the term per experiment; None when the candidate enters more than
        one channel, or its channel has no estimate.
    """
    where = [(states[i], cols) for i, cols in cand.equations.items()] + \
        [(f"output {outputs[j]}", cols) for j, cols in (cand.outputs or {}).items()]
    if len(where) != 1:
        return None
    name, cols = where[0]
    est = next((e for e in shape.estimates if e.equation == name), None)
    return None if est is None else (est, [np.ravel(c) for c in cols])


def agreement_with_shape(shape: ShapeResult, cand: Candidate, states: list[str], outputs: list[str]) -> ShapeFit | None:
    """How much of the learned disturbance of its channel a candidate law explains.

    Parameters
    ----------
    shape : ShapeResult
        The shape learned at the fit the candidate was screened at.
    cand : Candidate
        The candidate.
    states, outputs : list of str
        The names of the equation and output indices.

    Returns
    -------
    ShapeFit or None
        The agreement and the free smooth function's share; None for a candidate of several channels,
        a channel without an estimate, or a term that is constant or does not match the samples.
    """
    found = channel_of(shape, cand, states, outputs)
    if found is None:
        return None
    est, term = found
    g = np.concatenate(term) if term else np.zeros(0)
    if g.size != sum(d.size for d in est.d) or not np.all(np.isfinite(g)) or np.std(g) == 0:
        return None
    if est.variable is None:
        relate(est)   # only the most likely channels are related when the shape is learned
    return ShapeFit(channel=est.equation, agreement=shape_agreement(est, term), share=est.share_explained,
                    variable=est.variable)


def shape_note(shape: ShapeResult | None, cand: Candidate, states: list[str], outputs: list[str]) -> str:
    """"approximates; not identified: ..." for a law that lacks the learned shape; "" otherwise.

    Parameters
    ----------
    shape : ShapeResult or None
        The shape learned at the fit the candidate was screened at (None: no test).
    cand : Candidate
        The candidate.
    states, outputs : list of str
        The names of the equation and output indices.

    Returns
    -------
    str
        The note when the law explains `SHAPE_DISAGREEMENT` less of the disturbance than a smooth
        function of its best variable does; "" when it does not, or it cannot be judged.
    """
    fit = agreement_with_shape(shape, cand, states, outputs) if shape is not None else None
    if fit is None or fit.share is None or fit.agreement >= fit.share - SHAPE_DISAGREEMENT:
        return ""
    where = fit.channel if fit.channel.startswith("output ") else f"d{fit.channel}/dt"
    return (f"approximates; not identified: its law explains {100 * fit.agreement:.0f} % of the disturbance learned "
            f"on {where}, a smooth function of {fit.variable} {100 * fit.share:.0f} %")


def excess_over_noise(fit: FitResult, shape: ShapeResult) -> tuple[float, float] | None:
    """(Σ over outputs of (RMSE/σ)² − 1 where positive, the largest RMSE/σ) of a fit, σ the learned noise level.

    Parameters
    ----------
    fit : FitResult
        The fit (its RMSE per output).
    shape : ShapeResult
        The shape step's noise level per output.

    Returns
    -------
    tuple of (float, float) or None
        The residual's excess over the noise in units of the noise variance, and the largest ratio;
        None when no output has both.
    """
    rmse = {o: v for o, v in fit.metrics.rmse.items() if v is not None and np.isfinite(v)}
    ratios = [float(rmse[o] / s) for o, s in shape.noise_level.items() if o in rmse and s > 0]
    if not ratios:
        return None
    return sum(max(r * r - 1.0, 0.0) for r in ratios), max(ratios)


def memory_objection(state: LoopState, r: Refitted, screening: Screening) -> RejectedCandidate | None:
    """A "shape" rejection of a law of the present variables added to a disturbance with memory, or None.

    Parameters
    ----------
    state : LoopState
        The search so far (its shape, learned at its fit).
    r : Refitted
        The refitted candidate.
    screening : Screening
        The screen it came from.

    Returns
    -------
    RejectedCandidate or None
        The rejection (see the module docstring); None when the shape is not current, has no memory, looks
        like coloured noise, or the refit explains most of the residual's excess.
    """
    shape = state.shape
    if shape is None or state.shape_fit is not state.fit or not shape.estimates:
        return None
    best = shape.estimates[0]
    if best.share_explained is None or best.share_explained >= MEMORY_SHARE or best.residual_share < MEMORY_HOLDS \
            or looks_like_coloured_noise(shape):
        return None
    before, after = excess_over_noise(state.fit, shape), excess_over_noise(r.fit, shape)
    if before is None or after is None or before[0] <= 0 or after[1] <= UNEXPLAINED_RATIO:
        return None
    removed = (before[0] - after[0]) / before[0]
    if removed >= MIN_EXCESS_SHARE:
        return None
    where = best.equation if best.equation.startswith("output ") else f"d{best.equation}/dt"
    return rejected(r, screening, "shape", (
        f"the disturbance learned on {where} holds {100 * best.residual_share:.0f} % of the residual and no smooth "
        f"function of one variable explains more than {100 * best.share_explained:.0f} % of it (it depends on more, "
        f"e.g. on its history): this law removes {100 * removed:.0f} % of the residual's excess over the noise and "
        f"leaves it {after[1]:.1f}x the noise level; a stand-in, not the missing term"))
