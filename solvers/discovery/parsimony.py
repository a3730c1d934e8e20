"""Parsimony: what a refit that passed the evidence gates must still show to be added.

- A catch-all (a switching coefficient, a step or drift in time, an input delay) is never kept where a
  named law refitted at the same fit explained more but was rejected on its t-value alone (its size is
  not determined on these data; the catch-all would stand in for it); it is kept only if it
  improves the validation records (when there are some), never to pile a small coefficient
  (< `PILE_MIN_RELATIVE` of the parameter it changes) onto an accepted effect, and never when it moves
  the declared parameters far outside their intervals (more than `STAND_IN_SIGMAS` standard errors and
  `STAND_IN_RELATIVE` of the value) unless the validation records back the move (their error falls by
  `BACKED_BY_VALIDATION`): a term that does is a stand-in (`catch_all_objection`).
- Any refit must not make the validation records worse (`validation_objection`).
- A named law that moves the declared parameters so after the first step is kept but labelled
  `approximates` (`stand_in_verdict`).

The learned shape's tests (what a law must explain of it) are in `shape_test`.
"""
from __future__ import annotations

from typing import Literal

from greyfit.schemas.discovery import DiscoverRequest, RejectedCandidate, ValidationSummary
from greyfit.solvers.discovery.confirm import LoopState, Refitted
from greyfit.solvers.discovery.summary import equation_names, mean_nrmse, validation_worse
from greyfit.solvers.screening.screening import Screening

PILE_MIN_RELATIVE = 0.1
STAND_IN_SIGMAS = 5.0
STAND_IN_RELATIVE = 0.1
BACKED_BY_VALIDATION = 0.2   # a move is backed when the validation error falls by this share


def validation_objection(request: DiscoverRequest, r: Refitted, before: ValidationSummary | None,
                         screening: Screening) -> RejectedCandidate | None:
    """A "validation" rejection when the refit makes the validation records worse, or None.

    Parameters
    ----------
    request : DiscoverRequest
        The discovery request (its `validation_tolerance`).
    r : Refitted
        The refitted candidate, with its validation metrics.
    before : ValidationSummary or None
        Validation of the model before the candidate.
    screening : Screening
        The screen the candidate came from.

    Returns
    -------
    RejectedCandidate or None
        The rejection, naming the outputs that got worse; None when none did (or there are no records).
    """
    worse = validation_worse(before, r.validation, request.discovery.validation_tolerance)
    if not worse:
        return None
    return rejected(r, screening, "validation", f"better on the estimation data (BIC -{r.bic_drop:.0f}) but worse "
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
    stronger = [(law, drop) for at, law, drop in state.undetermined
                if at is state.fit and drop >= r.bic_drop and law.same_place(c)]
    if stronger:
        law, drop = max(stronger, key=lambda x: x[1])
        return rejected(r, screening, "parsimony",
                        f"a named law explains more here ({law.effect}: {law.term}, BIC drop {drop:.0f} against "
                        f"{r.bic_drop:.0f}) but its coefficient is not determined on these data (t-value below "
                        "the gate): a catch-all would stand in for it")
    if state.steps and c.modifies in r.fit.parameters and r.params:
        size = abs(r.fit.parameters[c.modifies].value) or 1.0
        rel = max(abs(r.fit.parameters[n].value) for n in r.params) / size
        if rel < PILE_MIN_RELATIVE:
            return rejected(r, screening, "parsimony", f"a catch-all coefficient of {100 * rel:.2g} % of {c.modifies} "
                                                       "would be piled onto the effect already accepted")
    if before_val is not None:
        a, b = mean_nrmse(before_val), mean_nrmse(r.validation)
        tol = request.discovery.validation_tolerance
        if a is not None and (b is None or b > a * (1 - tol)):
            shown = "n/a" if b is None else f"{b:.4g}"
            return rejected(r, screening, "parsimony", f"a catch-all kept only if it improves the validation records; "
                                                       f"mean NRMSE {a:.4g} -> {shown}")
    moved = moved_parameters(request, state, r, before_val)
    if state.steps and moved:
        return rejected(r, screening, "parsimony", "a catch-all that moves the declared parameters far outside their "
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
    a, b = mean_nrmse(before_val), mean_nrmse(r.validation)
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


def rejected(r: Refitted, screening: Screening, reason: Literal["validation", "parsimony", "shape"],
             detail: str) -> RejectedCandidate:
    """A refitted candidate as a rejection with its reason and detail.

    Parameters
    ----------
    r : Refitted
        The refitted candidate.
    screening : Screening
        The screen it came from (for the equation names).
    reason : {"validation", "parsimony", "shape"}
        The rejection's reason.
    detail : str
        Why, for the report.

    Returns
    -------
    RejectedCandidate
        The rejection.
    """
    c = r.sc.candidate
    return RejectedCandidate(effect=c.effect, equation=equation_names(screening, c), term=c.term, reason=reason,
                             detail=detail)
