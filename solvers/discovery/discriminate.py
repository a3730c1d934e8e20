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

A catch-all is a symptom (`catch_all`): the laws its values line up with, and any lag beside a delay,
are refitted beside it; a law within `AMBIGUOUS_BIC` of it goes ahead; one that wins all the same
while it lines up with a law, or follows an approximation, is at most `approximates`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from greyfit.schemas.discovery import DiscoverRequest, RejectedCandidate, RunnerUp, ValidationSummary
from greyfit.solvers.discovery.budget import contender_limits
from greyfit.solvers.discovery.catch_all import catch_all_cap, pointed_laws, prefer_law
from greyfit.solvers.discovery.confirm import (
    REFIT_MAX_ITER,
    LoopState,
    Refitted,
    bic,
    refit_candidate,
    timed_validation,
)
from greyfit.solvers.discovery.parsimony import catch_all_objection, stand_in_verdict, validation_objection
from greyfit.solvers.discovery.refit_test import AR_MAX_ORDER, ar_coefficients, residual_series, whiten
from greyfit.solvers.discovery.revise import accept
from greyfit.solvers.discovery.shape_test import memory_objection, shape_note
from greyfit.solvers.discovery.summary import equation_names, mean_nrmse
from greyfit.solvers.errors import FitError
from greyfit.solvers.screening.candidate import Candidate
from greyfit.solvers.screening.screening import Scored, Screening

MARGIN = 0.2                 # contenders explain at least (1 − MARGIN) of what the leader explains
MAX_CONTENDERS = 3           # refits per round, the leader included ...
MAX_NAMED_BESIDE_SERIES = 2  # ... and beyond them the named laws of an approximating candidate's variables
SAME_ON_THESE_DATA = 0.9999  # projected columns this correlated are one hypothesis on these data
AMBIGUOUS_BIC = 10.0         # whitened ΔBIC below which the estimation data do not tell two refits apart


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
    failed: list[Failed] = []
    refitted: list[Candidate] = []
    try:
        for k, group in enumerate(groups):
            if state.refits_left <= 0 or not state.clock.allows():
                break
            mark = len(state.refit_costs)
            r = refit_candidate(request, state, group, screening)
            refitted.append(group[0].candidate)
            if k == 0:   # the contenders' bounds, from what the leader's refits took (`budget`)
                state.limits = contender_limits(state.refit_costs[mark:], REFIT_MAX_ITER)
            _judge(request, state, r, group[0].candidate, before_val, screening, kept, failed)
    finally:
        state.limits = None
    kept += named_laws_beside_kept_series(request, state, kept, failed, before_val, screening)
    offered = pointed_laws(request, state, screening, kept, variants_of, lambda r, sc: _judge(
        request, state, r, sc.candidate, before_val, screening, kept, failed))
    state.undetermined += [(state.fit, f.refit.sc.candidate, f.refit.bic_drop) for f in failed
                           if f.refit is not None and f.refit.only_t and not f.refit.sc.candidate.approximating
                           and not f.refit.sc.candidate.catch_all]
    if not kept:
        return False
    winner, runners, verdict, separate = choose(request, state, kept, screening)
    runners += failed_runners(winner, kept, failed, screening)
    verdict, note = stand_in_verdict(request, state, winner, verdict, before_val)
    if verdict != "approximates":
        verdict, note = approximation_verdict(state, winner, verdict, refitted, screening)
    if verdict != "approximates":
        verdict, note = catch_all_cap(state, winner, verdict, offered)
    note = "; ".join(x for x in (note, winner.profiled) if x)
    design = _design_pointer(winner, kept, runners) if verdict == "ambiguous" else None
    accept(request, state, winner, screening, note=note, verdict=verdict, runners_up=runners, separate_by=separate,
           design=design)
    return True


def _design_pointer(winner: Refitted, kept: list[Refitted], runners: list[RunnerUp]) -> dict | None:
    """The T-optimal design request (POST /v1/designs) telling the winner from the runners-up the data tie with."""
    from greyfit.solvers.design.pointer import discrimination_request
    tied = {(r.effect, r.term) for r in runners if r.delta_bic is not None and r.delta_bic < AMBIGUOUS_BIC}
    rivals = [(r.sc.candidate.effect, r.model, r.fit) for r in kept
              if r is not winner and (r.sc.candidate.effect, r.sc.candidate.term) in tied]
    if not rivals:
        return None
    try:
        return discrimination_request(winner.sc.candidate.effect, winner.model, winner.fit, winner.request, rivals)
    except (ValueError, KeyError, IndexError):   # a record the frame cannot be read from: no pointer, no failure
        return None


@dataclass
class Failed:
    """A contender not kept: its candidate, why, and its refit when one converged (for its ΔBIC)."""

    candidate: Candidate
    why: str
    refit: Refitted | None = None


def _judge(request: DiscoverRequest, state: LoopState, r: Refitted | RejectedCandidate, head: Candidate,
           before_val: ValidationSummary | None, screening: Screening, kept: list[Refitted],
           failed: list[Failed]) -> None:
    """Apply the shape, parsimony and validation objections to a refit: into `kept`, or `failed` and rejected."""
    if isinstance(r, RejectedCandidate):
        rejection, refit = r, None
    elif r.rejection is not None:
        rejection, refit = r.rejection, r
    else:
        objection = memory_objection(state, r, screening) or catch_all_objection(
            request, state, r, before_val, screening) or validation_objection(request, r, before_val, screening)
        if objection is None:
            kept.append(r)
            return
        rejection, refit = objection, r
    state.rejected.append(rejection)
    failed.append(Failed(head, f"rejected ({rejection.reason})", refit))


def named_laws_beside_kept_series(request: DiscoverRequest, state: LoopState, kept: list[Refitted],
                                  failed: list[Failed], before_val: ValidationSummary | None,
                                  screening: Screening) -> list[Refitted]:
    """Named laws rejected on their coefficient's t-value alone, beside a kept series member of the
    same variables in the same place: back into the comparison, which the BIC decides.

    The series member's evidence shows that a term in those variables is there; which law it is, is
    what the comparison is for. A named law's coefficient can be nearly collinear with a declared
    parameter (quadratic drag ω|ω| with a linear damping bω), so its t-value is low under coloured
    noise while the likelihood ratio and BIC confirm it, and a series member less collinear with the
    declared terms (ω³) passed the t gate and won by the named law's absence: on a pendulum under
    AR(1) noise with a held input, 2 of 10 seeds named ω³ though quadratic drag was better by a
    whitened ΔBIC of 38-46.

    Parameters
    ----------
    request : DiscoverRequest
        The discovery request (options, validation experiments).
    state : LoopState
        The search so far; a law taken back has its rejection removed from `state.rejected`.
    kept : list of Refitted
        The refits that passed the gates.
    failed : list of Failed
        The contenders rejected; a law taken back is removed.
    before_val : ValidationSummary or None
        The validation before this round.
    screening : Screening
        The screen they came from.

    Returns
    -------
    list of Refitted
        The laws taken back (their `rejection` cleared), to join `kept`.
    """
    series = [r.sc.candidate for r in kept if r.sc.candidate.approximating and r.sc.candidate.variables]
    out: list[Refitted] = []
    for f in list(failed):
        r = f.refit
        if r is None or not r.only_t or r.rejection is None:
            continue
        c = r.sc.candidate
        if c.approximating or c.catch_all or not c.variables or not any(
                set(c.variables) == set(s.variables) and c.same_place(s) for s in series):
            continue
        if (memory_objection(state, r, screening) or catch_all_objection(request, state, r, before_val, screening)
                or validation_objection(request, r, before_val, screening)):
            continue
        state.rejected.remove(r.rejection)
        failed.remove(f)
        r.rejection = None
        out.append(r)
    return out


def failed_runners(winner: Refitted, kept: list[Refitted], failed: list[Failed],
                   screening: Screening) -> list[RunnerUp]:
    """The contenders not kept as runners-up: with their whitened ΔBIC to the winner where their refit
    converged (under the noise model of the kept refits, as `choose` compares those), else none.

    Parameters
    ----------
    winner : Refitted
        The chosen refit.
    kept : list of Refitted
        The refits that passed the gates (they fix the noise model of the comparison).
    failed : list of Failed
        The contenders rejected, with their refits where they converged.
    screening : Screening
        The screen they came from.

    Returns
    -------
    list of RunnerUp
        One per rejected contender (other than the winner's candidate), outcome "rejected (reason)".
    """
    others = [f for f in failed if f.candidate is not winner.sc.candidate]
    with_refit = [f.refit for f in others if f.refit is not None]
    bics = whitened_bics(kept, with_refit)
    best = bics[next(i for i, r in enumerate(kept) if r is winner)]
    gaps = dict(zip((id(r) for r in with_refit), bics[len(kept):]))
    out = []
    for f in others:
        c = f.candidate
        gap = gaps.get(id(f.refit)) if f.refit is not None else None
        out.append(RunnerUp(effect=c.effect, equation=equation_names(screening, c), term=c.term,
                            delta_bic=None if gap is None or not math.isfinite(gap - best) else float(gap - best),
                            validation_nrmse=mean_nrmse(f.refit.validation) if f.refit is not None else None,
                            outcome=f.why))
    return out


def approximation_verdict(state: LoopState, winner: Refitted, verdict: str, refitted: list[Candidate],
                          screening: Screening) -> tuple[str, str]:
    """An approximating winner, or a law without the learned shape, approximates: (verdict, note).

    A member of a series (a power, a smooth p(x): `Candidate.approximating`) that won over a named law
    of the same variables refitted beside it describes these data better than that law, but names no
    mechanism (it may stand in for a law the library lacks); and a law that explains much less of the
    learned disturbance than a free smooth function does not have its shape (`shape_test.shape_note`).

    Parameters
    ----------
    state : LoopState
        The search so far (its shape, when learned at its fit).
    winner : Refitted
        The chosen refit.
    verdict : str
        The verdict so far ("identified" or "ambiguous").
    refitted : list of Candidate
        The candidates refitted this round (the winner's included).
    screening : Screening
        The screen they came from.

    Returns
    -------
    tuple of (str, str)
        ("approximates", why) for an identified winner as above; an ambiguous one keeps its verdict with
        the note; else (verdict, "").
    """
    c = winner.sc.candidate
    named = [o for o in refitted if o is not c and not o.approximating and not o.catch_all
             and o.variables and set(o.variables) == set(c.variables)]
    note = ""
    if c.approximating and named:
        laws = ", ".join(dict.fromkeys(o.effect for o in named))
        note = (f"approximates; not identified: a member of a series that describes these data better than the "
                f"named law(s) of {', '.join(c.variables)} refitted beside it ({laws}), and names no mechanism")
    shape = state.shape if state.shape_fit is state.fit else None
    note = note or shape_note(shape, c, screening.states, screening.outputs)
    if not note:
        return verdict, ""
    return ("approximates" if verdict == "identified" else verdict), note


def variants_of(screening: Screening, sc: Scored) -> list[Scored]:
    """What is refitted for a candidate: a smoothed switch once at its widest significant width (the
    width is refined after, `revise.refine_width`); a family with variants (input delays) its two
    best; anything else itself (also a candidate refitted though not significant, `named_beside_series`).

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
                and s.scored_on == sc.scored_on] or [sc]   # a named law refitted beside a series unscreened
    if sc.candidate.width > 0:
        return [max(siblings, key=lambda s: s.candidate.width)]
    if sc.candidate.refit_variants:
        return siblings[:2]
    return [sc]


def contenders(screening: Screening, lead: Scored, state: LoopState) -> list[list[Scored]]:
    """The leader's variants and those of every significant candidate of another family within
    `MARGIN` of its explained variance, by screening BIC drop (beside a catch-all leader, by the share
    explained); catch-alls only beside a catch-all leader; an approximating series member whose
    projected column equals an earlier one's is the same hypothesis.

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
    for sc in _one_per_family(screening, lead):
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
    chosen += named_beside_series(screening, chosen, state)
    chosen += lines_beside_staircases(screening, chosen, state)
    return [variants_of(screening, sc) for sc in chosen]


def _one_per_family(screening: Screening, lead: Scored) -> list[Scored]:
    """The screen's candidates in the order contenders are drawn from them: beside a named law, the
    screen's rank; beside a catch-all, each family's variant on the leader's residual (else its
    first) by the share it explains.

    Symptoms compete on equal terms, the one that explains most of the same residual first: the screen's
    rank puts a change in time behind other shapes while a refit-only law is pending, and a drift
    explaining 99 % of the output residual was left out of the round a delay explaining 26 % led (the
    drift's first variant in rank was the one on the equation residuals, explaining less).
    """
    if not lead.candidate.catch_all:
        return screening.scored
    best: dict[str, Scored] = {}
    for sc in screening.scored:
        if not sc.significant:
            continue
        fam, held = sc.candidate.family, best.get(sc.candidate.family)
        if held is None or (sc.scored_on == lead.scored_on,
                            sc.score.explained) > (held.scored_on == lead.scored_on, held.score.explained):
            best[fam] = sc
    return sorted(best.values(), key=lambda sc: (sc.scored_on != lead.scored_on, -sc.score.explained))


def lines_beside_staircases(screening: Screening, chosen: list[Scored], state: LoopState) -> list[Scored]:
    """The simplest change in time of each parameter a chosen staircase (steps at searched
    times) changes: its drift, refitted beside it, significant at the screen or not.

    A parameter that drifts is approximated by a staircase as well as by its line, and the staircase's
    columns, several and placed by search, screen higher on a residual the biased base fit has bent;
    refitted side by side the line wins by BIC once the switch times count as parameters
    (`whitened_bics`), and without it the staircase of another parameter of the same equation can take
    the round.

    Parameters
    ----------
    screening : Screening
        The screen, ranked.
    chosen : list of Scored
        The candidates chosen so far.
    state : LoopState
        The search so far (families already tried are left out).

    Returns
    -------
    list of Scored
        One per staircase's parameter, the best screened first.
    """
    stairs = {sc.candidate.modifies for sc in chosen
              if sc.candidate.record_specific and sc.candidate.searched > 0 and sc.candidate.modifies}
    seen = {sc.candidate.family for sc in chosen}
    out: list[Scored] = []
    for sc in screening.scored:
        c = sc.candidate
        if (c.record_specific and c.searched == 0 and c.modifies in stairs and c.family not in seen
                and c.family not in state.tried and sc.score.bic_drop > 0):
            seen.add(c.family)
            out.append(sc)
    return out


def named_beside_series(screening: Screening, chosen: list[Scored], state: LoopState) -> list[Scored]:
    """The named laws of the same variables as an approximating candidate already chosen, in the same
    equation or output: always refitted beside it, significant at the screen or not, within the margin
    or not (the linearised screen understates a nonlinear law, and a series member that fits as well
    must not win by their absence). At most `MAX_NAMED_BESIDE_SERIES`.

    Parameters
    ----------
    screening : Screening
        The screen, ranked.
    chosen : list of Scored
        The candidates chosen so far (the leader first).
    state : LoopState
        The search so far (families already tried are left out).

    Returns
    -------
    list of Scored
        The named laws to add, the significant first, then by the share explained, one per family.
    """
    series = [sc.candidate for sc in chosen if sc.candidate.approximating and sc.candidate.variables]
    seen = {sc.candidate.family for sc in chosen}
    out: list[Scored] = []
    # significant first, then by the share explained: the BIC drop's effective sample size penalises a
    # law that leaves a slightly more correlated residual (T⁴ on a radiation record: the most explained,
    # 44 against the series' 1880)
    for sc in sorted(screening.scored, key=lambda x: (x.significant, x.score.explained), reverse=True):
        c = sc.candidate
        if c.approximating or c.catch_all or c.refit_only or c.family in seen or c.family in state.tried \
                or not c.variables:
            continue
        if any(set(c.variables) == set(s.variables) and c.same_place(s) for s in series):
            seen.add(c.family)
            out.append(sc)
    return out[:MAX_NAMED_BESIDE_SERIES]


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
    order = prefer_law(order, kept, bics, AMBIGUOUS_BIC)   # a law the data cannot tell from a catch-all
    vals = [mean_nrmse(r.validation) for r in kept]
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


def whitened_bics(kept: list[Refitted], others: list[Refitted] | tuple = ()) -> list[float]:
    """BIC of each refit on its output residuals whitened by the AR model of the plainly best kept one's
    residual (per experiment and output), so every refit is judged under the same noise model.

    Parameters
    ----------
    kept : list of Refitted
        The refits to compare (the reference is the one of them with the least plain BIC).
    others : list of Refitted
        Further refits judged under the same noise model (rejected contenders, for their ΔBIC).

    Returns
    -------
    list of float
        One BIC per refit, `kept` then `others` (inf where its residual cannot be simulated; the plain
        BICs when the reference's cannot).
    """
    every = [*kept, *others]
    ref = min(kept, key=lambda r: bic(r.fit))
    try:
        ref_series = residual_series(ref.request, ref.fit)
    except (FitError, RuntimeError, ValueError):
        return [bic(r.fit) for r in every]
    phis = []
    for series_ref in ref_series:
        ok = series_ref[np.isfinite(series_ref)]
        phis.append(ar_coefficients(ok, min(AR_MAX_ORDER, ok.size // 10)) if ok.size >= 20 else np.zeros(0))
    out = []
    for r in every:
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
        # a switch time placed by search is a parameter the refit does not carry
        out.append(total + (r.fit.metrics.nvarys + r.sc.candidate.searched) * math.log(max(n_all, 2)))
    return out


def _validation_now(request: DiscoverRequest, state: LoopState) -> ValidationSummary | None:
    if not request.validation:
        return None
    return timed_validation(request, state, state.model, state.fit)


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
