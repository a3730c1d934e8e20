"""Discriminate by refit, not by screen; keep catch-alls for what no named law explains.

The linearised screen ranks candidates, but near-equivalent laws (a sensor offset and a source
offset; T⁴ − Ta⁴ and (T − Ta)|T − Ta| over a narrow range) score within a few per cent of each other
and the first is not always right. So every significant candidate of another family whose screening
evidence is within `MARGIN` of the leader's is refitted beside it (at most `MAX_CONTENDERS`), each
within a multiple of the leader's refit iterations (`budget.contender_limits`: one cut there is not
decided, and reported so), and the refits are compared by BIC on output residuals whitened by one
AR noise model (coloured noise is not evidence) and on the validation records. Two that the
estimation data do not tell apart (whitened ΔBIC < `AMBIGUOUS_BIC`) and the validation records do
not either are reported `ambiguous`, with both named and what would separate them.

Parsimony. A catch-all (a switching coefficient, a step or drift in time, an input delay) joins only a
round no named law leads; it is kept only if it improves the validation records (when there are
some), never to pile a small coefficient (< `PILE_MIN_RELATIVE` of the parameter it changes) onto an
accepted effect, and never when it moves the declared parameters far outside their intervals (more
than `STAND_IN_SIGMAS` standard errors and `STAND_IN_RELATIVE` of the value) unless the validation
records back the move (their error falls by `BACKED_BY_VALIDATION`): a term that does is a stand-in.
A named law that does so after the first step is kept but labelled `approximates`.
"""
from __future__ import annotations

import math
from typing import Literal

import numpy as np

from greyfit.schemas.discovery import DiscoverRequest, RejectedCandidate, RunnerUp, ValidationSummary
from greyfit.solvers.discovery.budget import contender_limits
from greyfit.solvers.discovery.candidate import Candidate
from greyfit.solvers.discovery.confirm import (
    REFIT_MAX_ITER,
    LoopState,
    Refitted,
    bic,
    refit_candidate,
    timed_validation,
)
from greyfit.solvers.discovery.refit_test import AR_MAX_ORDER, ar_coefficients, residual_series, whiten
from greyfit.solvers.discovery.revise import accept
from greyfit.solvers.discovery.screening import Scored, Screening
from greyfit.solvers.discovery.summary import equation_names, validation_worse
from greyfit.solvers.errors import FitError

MARGIN = 0.2                 # contenders explain at least (1 − MARGIN) of what the leader explains
MAX_CONTENDERS = 3           # refits per round, the leader included
SAME_ON_THESE_DATA = 0.9999  # projected columns this correlated are one hypothesis on these data
AMBIGUOUS_BIC = 10.0         # whitened ΔBIC below which the estimation data do not tell two refits apart
PILE_MIN_RELATIVE = 0.1
STAND_IN_SIGMAS = 5.0
STAND_IN_RELATIVE = 0.1
BACKED_BY_VALIDATION = 0.2   # a move is backed when the validation error falls by this share


def discriminate(request: DiscoverRequest, state: LoopState, screening: Screening, lead: Scored) -> bool:
    """Refit `lead` and its contenders, keep the best by whitened BIC and validation; True if one is added.

    Parameters
    ----------
    request : DiscoverRequest
        The discovery request (options, validation experiments).
    state : LoopState
        The search so far (model, fit, steps, refits left, budget).
        Updated: tried families, rejected candidates, and the accepted step.
    screening : Screening
        The screen the candidate came from.
    lead : Scored
        The best significant candidate not yet tried.

    Returns
    -------
    bool
        True when a candidate was accepted.
    """
    groups = contenders(screening, lead, state)
    state.tried.update(g[0].candidate.family for g in groups)
    before_val = _validation_now(request, state)
    kept: list[Refitted] = []
    failed: list[tuple[Candidate, str]] = []
    try:
        for k, group in enumerate(groups):
            if state.refits_left <= 0 or not state.clock.allows():
                break
            mark = len(state.refit_costs)
            r = refit_candidate(request, state, group, screening)
            if k == 0:   # the contenders' bounds, from what the leader's refits took (`budget`)
                state.limits = contender_limits(state.refit_costs[mark:], REFIT_MAX_ITER)
            if not isinstance(r, RejectedCandidate):
                objection = catch_all_objection(request, state, r, before_val, screening) or \
                    _validation_objection(request, r, before_val, screening)
                if objection:
                    r = objection
            if isinstance(r, RejectedCandidate):
                state.rejected.append(r)
                failed.append((group[0].candidate, f"rejected ({r.reason})"))
            else:
                kept.append(r)
    finally:
        state.limits = None
    if not kept:
        return False
    winner, runners, verdict, separate = choose(request, state, kept, screening)
    runners += [RunnerUp(effect=c.effect, equation=equation_names(screening, c), term=c.term, delta_bic=None,
                         outcome=why) for c, why in failed if c is not winner.sc.candidate]
    verdict, note = stand_in_verdict(request, state, winner, verdict, before_val)
    accept(request, state, winner, screening, note=note, verdict=verdict, runners_up=runners, separate_by=separate)
    return True


def variants_of(screening: Screening, sc: Scored) -> list[Scored]:
    """What is refitted for a candidate: a smoothed switch once at its widest significant width (the
    width is refined after, `revise.refine_width`); a family with variants (input delays) its two
    best; anything else itself.

    Parameters
    ----------
    screening : Screening
        The screen.
    sc : Scored
        The candidate.

    Returns
    -------
    list of Scored
        The variants to refit (one or two).
    """
    fam = sc.candidate.family
    siblings = [s for s in screening.scored if s.significant and s.candidate.family == fam
                and s.scored_on == sc.scored_on]
    if sc.candidate.width > 0:
        return [max(siblings, key=lambda s: s.candidate.width)]
    if sc.candidate.refit_variants:
        return siblings[:2]
    return [sc]


def contenders(screening: Screening, lead: Scored, state: LoopState) -> list[list[Scored]]:
    """The leader's variants and those of every significant candidate of another family within
    `MARGIN` of its explained variance, by screening BIC drop; catch-alls only beside a catch-all
    leader; an approximating series member whose projected column equals an earlier one's is the same
    hypothesis.

    Parameters
    ----------
    screening : Screening
        The screen, ranked.
    lead : Scored
        The leader.
    state : LoopState
        The search so far (families already tried are left out).

    Returns
    -------
    list of list of Scored
        At most `MAX_CONTENDERS` groups, the leader's first, each the variants to refit (`variants_of`).
    """
    floor = (1 - MARGIN) * lead.score.explained
    chosen = [lead]
    seen = {lead.candidate.family}
    pools: dict[bool, list[Scored]] = {False: [], True: []}   # named laws, approximating series
    for sc in screening.scored:
        c = sc.candidate
        if (not sc.significant or c.family in seen or c.family in state.tried or sc.score.explained < floor
                or (c.catch_all and not lead.candidate.catch_all) or c.refit_only):
            continue
        seen.add(c.family)
        pools[c.approximating].append(sc)
    # named laws and approximating series in turn, each by screening rank: a power series that
    # screens best does not crowd the named law out of the refits (nor the other way round)
    turn = not lead.candidate.approximating
    while len(chosen) < MAX_CONTENDERS and (pools[False] or pools[True]):
        pool = pools[turn] or pools[not turn]
        sc = pool.pop(0)
        # a power or a smooth law equal on these data to one already in is a re-parametrisation of it;
        # two named laws equal on these data are the ambiguity this step exists to report
        if not (sc.candidate.approximating and any(_same_hypothesis(sc, other) for other in chosen)):
            chosen.append(sc)
        turn = not turn
    return [variants_of(screening, sc) for sc in chosen]


def _same_hypothesis(a: Scored, b: Scored) -> bool:
    if a.scorer is None or a.scorer is not b.scorer or a.scored_on != b.scored_on:
        return False
    try:
        ga = a.scorer.stack(a.candidate.equations, a.candidate.outputs)
        gb = b.scorer.stack(b.candidate.equations, b.candidate.outputs)
    except (ValueError, IndexError):
        return False
    if ga is None or gb is None or ga.ndim != 1 or gb.ndim != 1:
        return False
    pa, pb = a.scorer.project(ga), b.scorer.project(gb)
    na, nb = np.linalg.norm(pa), np.linalg.norm(pb)
    return bool(na > 0 and nb > 0 and abs(float(pa @ pb)) / (na * nb) > SAME_ON_THESE_DATA)


def choose(request: DiscoverRequest, state: LoopState, kept: list[Refitted],
           screening: Screening) -> tuple[Refitted, list[RunnerUp], str, str | None]:
    """(winner, runners-up, verdict, what would separate them) among refits that passed the gates.

    Parameters
    ----------
    request : DiscoverRequest
        The discovery request (options, validation experiments).
    state : LoopState
        The search so far.
    kept : list of Refitted
        The refits that passed, in screening order.
    screening : Screening
        The screen the candidate came from.

    Returns
    -------
    tuple of (Refitted, list of RunnerUp, str, str or None)
        The winner (lowest whitened BIC unless the validation records clearly prefer the second), the
        others as runners-up with their ΔBIC and outcome, the verdict ("identified" or "ambiguous"), and
        for an ambiguous one what data would separate them.
    """
    bics = whitened_bics(kept)
    # an exact tie (equivalent laws) keeps the screening order: the leader first
    order = sorted(range(len(kept)), key=lambda i: (round(bics[i], 3), i))
    vals = [_mean_nrmse(r.validation) for r in kept]
    best, second, verdict, separate = order[0], None, "identified", None
    if len(order) > 1:
        second = order[1]
        gap = bics[second] - bics[best]
        told = _validation_tells(vals[best], vals[second], request.discovery.validation_tolerance)
        if told == "second":
            best, second = second, best
        if (gap < AMBIGUOUS_BIC and told is None) or (gap >= AMBIGUOUS_BIC and told == "second"):
            verdict = "ambiguous"
            tied = [kept[i].sc.candidate for i in order if i != best and abs(bics[i] - bics[best]) < AMBIGUOUS_BIC]
            separate = separation_hint(kept[best].sc.candidate, tied or [kept[second].sc.candidate])
    runners = []
    for i in order:
        if i == best:
            continue
        c = kept[i].sc.candidate
        gap = float(bics[i] - bics[best])
        tie = verdict == "ambiguous" and (i == second or abs(gap) < AMBIGUOUS_BIC)
        outcome = ("as good on these data" if tie
                   else "worse on the validation records" if gap < AMBIGUOUS_BIC else "worse by refit")
        runners.append(RunnerUp(effect=c.effect, equation=equation_names(screening, c), term=c.term,
                                delta_bic=gap, validation_nrmse=vals[i], outcome=outcome))
    return kept[best], runners, verdict, separate


def _validation_tells(a: float | None, b: float | None, tol: float) -> str | None:
    """Which of two is better on the validation records, if clearly (by more than `tol` relative)."""
    if a is None or b is None:
        return None
    if b < a * (1 - tol):
        return "second"
    if a < b * (1 - tol):
        return "first"
    return None


def whitened_bics(kept: list[Refitted]) -> list[float]:
    """BIC of each refit on its output residuals whitened by the AR model of the plainly best one's
    residual (per experiment and output), so every refit is judged under the same noise model.

    Parameters
    ----------
    kept : list of Refitted
        The refits to compare.

    Returns
    -------
    list of float
        One BIC per refit (inf where its residual cannot be simulated; the plain BICs when the
        reference's cannot).
    """
    ref = min(kept, key=lambda r: bic(r.fit))
    try:
        ref_series = residual_series(ref.request, ref.fit)
    except (FitError, RuntimeError, ValueError):
        return [bic(r.fit) for r in kept]
    phis = []
    for series_ref in ref_series:
        ok = series_ref[np.isfinite(series_ref)]
        phis.append(ar_coefficients(ok, min(AR_MAX_ORDER, ok.size // 10)) if ok.size >= 20 else np.zeros(0))
    out = []
    for r in kept:
        try:
            series = residual_series(r.request, r.fit)
        except (FitError, RuntimeError, ValueError):
            out.append(float("inf"))
            continue
        total, n_all = 0.0, 0
        for s, phi in zip(series, phis):
            e = whiten(s[np.isfinite(s)], phi)
            if e.size:
                total += e.size * math.log(max(float(e @ e) / e.size, 1e-300))
                n_all += e.size
        out.append(total + r.fit.metrics.nvarys * math.log(max(n_all, 2)))
    return out


def _mean_nrmse(v: ValidationSummary | None) -> float | None:
    vals = [x for x in (v.nrmse.values() if v is not None else []) if x is not None and np.isfinite(x)]
    return float(np.mean(vals)) if vals else None


def _validation_now(request: DiscoverRequest, state: LoopState) -> ValidationSummary | None:
    if not request.validation:
        return None
    return timed_validation(request, state, state.model, state.fit)


def _validation_objection(request: DiscoverRequest, r: Refitted, before: ValidationSummary | None,
                          screening: Screening) -> RejectedCandidate | None:
    worse = validation_worse(before, r.validation, request.discovery.validation_tolerance)
    if not worse:
        return None
    return _rejected(r, screening, "validation", f"better on the estimation data (BIC -{r.bic_drop:.0f}) but worse "
                                                 f"on the validation records: {worse}")


def catch_all_objection(request: DiscoverRequest, state: LoopState, r: Refitted,
                        before_val: ValidationSummary | None, screening: Screening) -> RejectedCandidate | None:
    """Why a refitted catch-all is not kept (see the module docstring), or None.

    Parameters
    ----------
    request : DiscoverRequest
        The discovery request (options, validation experiments).
    state : LoopState
        The search so far (model, fit, steps, refits left, budget).
    r : Refitted
        The refitted candidate.
    before_val : ValidationSummary or None
        Validation of the model before the candidate.
    screening : Screening
        The screen the candidate came from.

    Returns
    -------
    RejectedCandidate or None
        A "parsimony" rejection when the candidate is a catch-all that piles a small coefficient onto an
        accepted effect, does not improve the validation records, or is a stand-in; None otherwise.
    """
    c = r.sc.candidate
    if not c.catch_all:
        return None
    if state.steps and c.modifies in r.fit.parameters and r.params:
        size = abs(r.fit.parameters[c.modifies].value) or 1.0
        rel = max(abs(r.fit.parameters[n].value) for n in r.params) / size
        if rel < PILE_MIN_RELATIVE:
            return _rejected(r, screening, "parsimony", f"a catch-all coefficient of {100 * rel:.2g} % of {c.modifies} "
                                                   "would be piled onto the effect already accepted")
    if before_val is not None:
        a, b = _mean_nrmse(before_val), _mean_nrmse(r.validation)
        tol = request.discovery.validation_tolerance
        if a is not None and (b is None or b > a * (1 - tol)):
            shown = "n/a" if b is None else f"{b:.4g}"
            return _rejected(r, screening, "parsimony", f"a catch-all kept only if it improves the validation records; "
                                                   f"mean NRMSE {a:.4g} -> {shown}")
    moved = moved_parameters(request, state, r, before_val)
    if state.steps and moved:
        return _rejected(r, screening, "parsimony", "a catch-all that moves the declared parameters far outside their "
                                               f"intervals is a stand-in: {moved}")
    return None


def stand_in_verdict(request: DiscoverRequest, state: LoopState, r: Refitted, verdict: str,
                     before_val: ValidationSummary | None) -> tuple[str, str]:
    """A named law added after the first step that moves the declared parameters far outside their
    intervals approximates something else, unless the validation records back the move (their error
    falls by `BACKED_BY_VALIDATION`): (verdict, note for the description).

    Parameters
    ----------
    request : DiscoverRequest
        The discovery request (options, validation experiments).
    state : LoopState
        The search so far (model, fit, steps, refits left, budget).
    r : Refitted
        The refitted candidate.
    verdict : str
        The verdict so far ("identified" or "ambiguous").
    before_val : ValidationSummary or None
        Validation of the model before the candidate.

    Returns
    -------
    tuple of (str, str)
        ("approximates", a note naming the moves) for such a law; else the verdict unchanged and "".
    """
    if not state.steps or r.sc.candidate.catch_all:
        return verdict, ""
    moved = moved_parameters(request, state, r, before_val)
    if not moved:
        return verdict, ""
    return "approximates", f"approximates; not identified: it moves {moved}"


def moved_parameters(request: DiscoverRequest, state: LoopState, r: Refitted,
                     before_val: ValidationSummary | None) -> str:
    """The declared parameters the refit moved by more than STAND_IN_SIGMAS standard errors of the fit
    before and STAND_IN_RELATIVE of their value, as text ('' when none, or when the validation records
    back the move: a second effect may well correct what the first left biased).

    Parameters
    ----------
    request : DiscoverRequest
        The discovery request (options, validation experiments).
    state : LoopState
        The search so far (model, fit, steps, refits left, budget).
    r : Refitted
        The refitted candidate.
    before_val : ValidationSummary or None
        Validation of the model before the candidate.

    Returns
    -------
    str
        "p old -> new (±stderr before)" for each such parameter, joined by ", "; or "".
    """
    a, b = _mean_nrmse(before_val), _mean_nrmse(r.validation)
    if a is not None and b is not None and b < (1 - BACKED_BY_VALIDATION) * a:
        return ""
    out = []
    for p in request.model.parameters:
        old, new = state.fit.parameters.get(p.name), r.fit.parameters.get(p.name)
        if p.fixed or p.per_experiment or old is None or new is None or not old.stderr:
            continue
        move = abs(new.value - old.value)
        if move > STAND_IN_SIGMAS * old.stderr and move > STAND_IN_RELATIVE * abs(old.value):
            out.append(f"{p.name} {old.value:.4g} -> {new.value:.4g} (±{old.stderr:.2g} before)")
    return ", ".join(out)


def separation_hint(a: Candidate, others: list[Candidate]) -> str:
    """What data would tell the chosen candidate apart from those as good on these data: the hint for
    the first of another kind (sensor against state, a law against a change in time), else the first.

    Parameters
    ----------
    a : Candidate
        The chosen candidate.
    others : list of Candidate
        Those as good on these data (at least one).

    Returns
    -------
    str
        The hint: another operating level or output, a second record, or a wider range of the variables.
    """
    b = next((o for o in others if bool(o.outputs) != bool(a.outputs) or o.record_specific != a.record_specific),
             others[0])
    if bool(a.outputs) != bool(b.outputs):
        sensor, other = (a, b) if a.outputs else (b, a)
        return (f"a record at another operating level (a different input level or offset), or a measurement of "
                f"another output: {sensor.term} changes only the reading, the same at every level, while "
                f"{other.term} changes the state itself and shows wherever that state acts")
    if a.record_specific or b.record_specific:
        return "a second record: a change in time of this record does not repeat in another, a law does"
    variables = sorted(set(a.variables) | set(b.variables))
    if variables:
        return (f"a record that takes {', '.join(variables)} over a wider range than here (e.g. a larger or "
                f"differently shaped input): {a.term} and {b.term} agree over the range seen and differ beyond it")
    return "a second record with a different input (level, amplitude or spectrum)"


def _rejected(r: Refitted, screening: Screening, reason: Literal["validation", "parsimony"],
              detail: str) -> RejectedCandidate:
    c = r.sc.candidate
    return RejectedCandidate(effect=c.effect, equation=equation_names(screening, c), term=c.term, reason=reason,
                             detail=detail)
