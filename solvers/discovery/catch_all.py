"""A catch-all is a symptom, not an answer: what a step, drift, switch or delay points to is refitted
beside it, and a catch-all that is not re-expressed so names no mechanism.

- **Line-up.** A change of a declared parameter in time (steps, a drift) or with a threshold (a
  switch) whose fitted contribution lines up with the column of a state- or input-dependent law in
  the same place (|correlation| ≥ `LINE_UP`, both with the fit's own parameters regressed out) is that
  law seen through a clock or a threshold: six steps of a heat-loss coefficient, each beside a heater
  change and with its sign, are a loss growing with temperature. The laws it lines up with (at most
  `MAX_POINTED`, best first) are offered and refitted beside it (`pointed_laws`).
- **A delay is compared with a lag.** Any first-order lag the library offers (a family whose effect
  names a lag: a sensor's or an actuator's) is refitted beside a leading delay: a thermocouple's lag
  mimics a dead time of a few samples.
- **Ties go to the law** (`prefer_law`): a named law within the ambiguity margin of a catch-all's
  whitened BIC is the answer; the catch-all becomes its runner-up.
- **At most `approximates`** (`catch_all_cap`): a catch-all that wins although it lines up with a law,
  or that follows steps the loop itself called `approximates` (what it patches is itself an
  approximation), is kept but labelled `approximates`.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from greyfit.schemas.discovery import DiscoverRequest, RejectedCandidate
from greyfit.solvers.discovery.confirm import LoopState, Refitted, refit_candidate
from greyfit.solvers.screening.screening import Scored, Screening

LINE_UP = 0.7     # |correlation| of the contributions above which a catch-all follows a law
MAX_POINTED = 2   # laws refitted beside a leading catch-all

Judge = Callable[[Refitted | RejectedCandidate, Scored], None]
Variants = Callable[[Screening, Scored], list[Scored]]


def line_up(a: Scored, b: Scored) -> float:
    """|correlation| of the fitted contribution of `a` with the column of `b` in the same regression.

    Parameters
    ----------
    a : Scored
        The catch-all (its columns are regressed on the residual; several switch times give one
        contribution).
    b : Scored
        The law (one column).

    Returns
    -------
    float
        In [0, 1]; 0 when the two were not scored in the same regression or a column is missing.
    """
    scorer = a.scorer
    if scorer is None or scorer is not b.scorer or a.scored_on != b.scored_on:
        return 0.0
    try:
        ga = scorer.stack(a.candidate.equations, a.candidate.outputs)
        gb = scorer.stack(b.candidate.equations, b.candidate.outputs)
    except (ValueError, IndexError):
        return 0.0
    if ga is None or gb is None or ga.shape[0] != gb.shape[0]:
        return 0.0
    pa = scorer.project(ga.reshape(ga.shape[0], -1))
    pb = scorer.project(gb.reshape(gb.shape[0], -1))[:, 0]
    if not (np.all(np.isfinite(pa)) and np.all(np.isfinite(pb))):
        return 0.0
    coef, *_ = np.linalg.lstsq(pa, scorer.r0, rcond=None)
    fa = pa @ coef
    na, nb = float(np.linalg.norm(fa)), float(np.linalg.norm(pb))
    return abs(float(fa @ pb)) / (na * nb) if na > 0 and nb > 0 else 0.0


def is_lag(sc: Scored) -> bool:
    """Whether a candidate is a first-order lag (of a sensor or an input), whichever family offers it.

    Parameters
    ----------
    sc : Scored
        The candidate.

    Returns
    -------
    bool
        True when its effect's name names a lag.
    """
    return "lag" in sc.candidate.effect.split("_")


def pointed_candidates(lead: Scored, screening: Screening, tried: set[str]) -> list[tuple[Scored, float]]:
    """The laws a leading catch-all points to, with their line-up (1.0 for a lag beside a delay).

    Parameters
    ----------
    lead : Scored
        The catch-all leading the round.
    screening : Screening
        The screen it came from.
    tried : set of str
        Families refitted already (not offered again).

    Returns
    -------
    list of tuple of (Scored, float)
        At most `MAX_POINTED`, one per family, the best lined-up first.
    """
    c = lead.candidate
    best: dict[str, tuple[Scored, float]] = {}
    for sc in screening.scored:
        o = sc.candidate
        if o.family in tried or o.family == c.family or (o.catch_all and not is_lag(sc)):
            continue   # a lag is a catch-all too, and the comparison a delay needs
        if c.lag > 0 and is_lag(sc):
            score = 1.0 + sc.score.explained   # every lag beside a delay: the best explained first
        elif c.modifies and (o.modifies == c.modifies or o.same_place(c)):
            score = line_up(lead, sc)
            if score < LINE_UP:
                continue
        else:
            continue
        if o.family not in best or score > best[o.family][1]:
            best[o.family] = (sc, score)
    ranked = sorted(best.values(), key=lambda x: -x[1])
    return [(sc, min(score, 1.0)) for sc, score in ranked[:MAX_POINTED]]


def pointed_laws(request: DiscoverRequest, state: LoopState, screening: Screening, kept: list[Refitted],
                 variants: Variants, judge: Judge) -> list[tuple[Scored, float]]:
    """Refit the laws the leading catch-all points to, when a catch-all leads the round's kept refits.

    Parameters
    ----------
    request : DiscoverRequest
        The discovery request.
    state : LoopState
        The search so far (its refits are counted; the families refitted join `tried`).
    screening : Screening
        The screen.
    kept : list of Refitted
        The refits of the round that passed the gates.
    variants : callable
        ``variants(screening, scored)``: what is refitted for a candidate.
    judge : callable
        ``judge(refit or rejection, scored)``: into the round's kept or failed refits.

    Returns
    -------
    list of tuple of (Scored, float)
        The laws offered (refitted, whatever their outcome), with their line-up.
    """
    if not kept:
        return []
    lead = min(kept, key=lambda r: r.fit.metrics.bic if r.fit.metrics.bic is not None else np.inf)
    if not lead.sc.candidate.catch_all:
        return []
    offered = pointed_candidates(lead.sc, screening, state.tried)
    for sc, _ in offered:
        if state.refits_left <= 0 or not state.clock.allows():
            break
        state.tried.add(sc.candidate.family)
        judge(refit_candidate(request, state, variants(screening, sc), screening), sc)
    return offered


def prefer_law(order: list[int], kept: list[Refitted], bics: list[float], margin: float) -> list[int]:
    """The order of the refits with a named law moved ahead of a leading catch-all within `margin`.

    Parameters
    ----------
    order : list of int
        Indices into `kept`, best whitened BIC first.
    kept : list of Refitted
        The refits.
    bics : list of float
        Their whitened BICs.
    margin : float
        The ΔBIC below which the data do not tell two refits apart.

    Returns
    -------
    list of int
        The order, a law first where a catch-all led by less than `margin`.
    """
    head = order[0]
    if not kept[head].sc.candidate.catch_all:
        return order
    law = next((i for i in order[1:] if not kept[i].sc.candidate.catch_all and bics[i] - bics[head] < margin),
               None)
    return order if law is None else [law, *[i for i in order if i != law]]


def catch_all_cap(state: LoopState, winner: Refitted, verdict: str,
                  offered: list[tuple[Scored, float]]) -> tuple[str, str]:
    """A catch-all winner's verdict, at most `approximates`, with the reason (see the module docstring).

    Parameters
    ----------
    state : LoopState
        The search so far (the steps already taken and their verdicts).
    winner : Refitted
        The chosen refit.
    verdict : str
        Its verdict so far.
    offered : list of tuple of (Scored, float)
        The laws the catch-all pointed to and were refitted beside it.

    Returns
    -------
    tuple of (str, str)
        ("approximates", why) for a catch-all that lines up with a law it did not become, or that
        follows an approximation; else (verdict, "").
    """
    c = winner.sc.candidate
    if not c.catch_all:
        return verdict, ""
    lined = [(sc, r) for sc, r in offered if not is_lag(sc)]
    if lined:
        sc, r = lined[0]
        return "approximates", (f"approximates; not identified: its values line up with "
                                f"{', '.join(sc.candidate.variables) or sc.candidate.term} (r = {r:.2f}), the "
                                f"{sc.candidate.effect} law refitted beside it did not explain it, and a "
                                f"{'change in time' if c.record_specific else 'switch'} names no mechanism")
    approximated = [s for s in state.steps if s.verdict == "approximates"]
    if approximated:
        return "approximates", ("approximates; not identified: a catch-all that follows steps the search itself "
                                f"calls approximations ({', '.join(s.effect for s in approximated)}) patches what "
                                "they leave, and names no mechanism")
    return verdict, ""
