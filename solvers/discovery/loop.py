"""Close the loop: fit, trace the residual to a named missing effect, add it, refit, report.

The steps, in the order they run:

1. Fit the declared model with the requested method (`fit_model`); simulate it on the validation
   experiments, if any.
2. Screen (`screening.screen`): every candidate of the effect library (`effects.library`, a registry
   of families in `families/`) is scored
   - on the equation residuals of measured states (`scoring_equations`), and
   - on the output residuals through the output sensitivities (`scoring_outputs`): effects in
     equations of unmeasured states and in the output path (`output_effects`) show there.
   A candidate is significant when its F-test p-value is below `significance` divided by the number
   of candidates tried (Bonferroni), it explains at least `min_explained` of the residual variance,
   and its sign is physical. One ranking: largest BIC drop first, a change in time (step, drift)
   behind a structural effect that explains nearly as much.
3. Discriminate and confirm (`discriminate.discriminate`, `confirm.refit_candidate`): the best
   significant candidate and its contenders of other families within a margin of its screening
   evidence are each added and the whole model refitted with the requested method, started one
   Gauss-Newton step from the old fit (`warm_start`). A refit passes if it converges, its BIC falls
   by `min_bic_drop`, its likelihood ratio with the noise allowed to be coloured passes the screen's
   Bonferroni level (`refit_test`), the new parameter has |value|/stderr ≥ `min_t_value` (or, where
   only that gate fails, its profile-likelihood interval at that level excludes 0:
   `confirm.profile_decides`), and the validation records do not get worse; a catch-all also under
   the parsimony rules and `catch_all`'s (what it lines up with is refitted beside it). When no
   significant candidate is confirmed, the best named law of each family with a screening BIC drop of
   `min_bic_drop` is refitted under the same gates (`refit_below_screen`). Of those that
   pass, the best by whitened BIC and validation is added, the others reported as its runners-up;
   two the data cannot tell apart make the step `ambiguous`. A smoothed switch is refitted at its
   widest significant width and the width refined after. What fails is recorded in `rejected` with
   the reason and the next ranked candidate is tried, within `max_refits` refits.
4. Repeat up to `max_terms`; report before/after (estimation and validation), each step's evidence
   and the augmented model. When nothing is added, the conclusion says why.

No screen or refit starts once `time_budget_s` is spent (`budget.Clock`, which also times each
phase for `DiscoveryResult.timings`). A contender's refit is bounded by iterations relative to its
leader's, and every refit's CPU time by a multiple of the base fit's (`budget.RefitLimits`).
"""
from __future__ import annotations

import time
from typing import Callable, Optional

import numpy as np

from greyfit.schemas.discovery import CandidateScore, DiscoverRequest, DiscoveryOptions, DiscoveryResult
from greyfit.schemas.fit import FitRequest, FitResult
from greyfit.solvers.data.preprocess import prepare_request
from greyfit.solvers.discovery.budget import Clock
from greyfit.solvers.discovery.confirm import LoopState, screen_state
from greyfit.solvers.discovery.discriminate import discriminate
from greyfit.solvers.discovery.ground import solid_ground
from greyfit.solvers.discovery.leftover import leftover_at
from greyfit.solvers.discovery.shape import shape_at
from greyfit.solvers.discovery.summary import (
    added_inputs,
    public_scores,
    steps_conclusion,
    summarize,
    validate,
    with_units,
)
from greyfit.solvers.errors import ModelDefinitionError
from greyfit.solvers.fit import fit_model
from greyfit.solvers.model.expressions import compile_expression
from greyfit.solvers.screening.screening import Scored, Screening

__all__ = ["discover", "LoopState", "try_in_rank_order", "Progress"]

# progress(phase, candidate, refits used): "base_fit", "screening", "refit" (candidate: the term
# refitted), "done" (candidate: the conclusion); for a progress line, never for control
Progress = Callable[[str, str, int], None]


def _silent(phase: str, candidate: str, refits: int) -> None:
    return None


def discover(request: DiscoverRequest, progress: Optional[Progress] = None) -> DiscoveryResult:
    """Fit, find and add missing effects, refit; see the module docstring for the tests used.

    Parameters
    ----------
    request : DiscoverRequest
        The model, the estimation and validation experiments, the fit method and options, and the
        discovery options (effects, user candidates, significance, budgets).
    progress : Progress or None
        ``progress(phase, candidate, refits)``, if given, is called as the search moves on (phase
        "base_fit", "screening", "refit" or "done"); for a progress line, never for control.

    Returns
    -------
    DiscoveryResult
        The conclusion, before/after summaries (estimation and validation), the accepted steps with
        their evidence, the rejected candidates, the first screen, notes, the augmented model and its
        fit, what is left unexplained with the learned disturbance shape, and the timings.

    Raises
    ------
    ModelDefinitionError
        When a user candidate names no state, reuses a name or does not compile, or the model does not
        compile; the field is named.
    DataError
        When the experiments do not fit the model (from the base fit).
    """
    opts = request.discovery
    tell = progress or _silent
    clock = Clock(opts.time_budget_s)
    check_user_candidates(request)
    # detrend/decimate/window once, for the fits and the screens alike
    asked = request.options.input_interpolation
    request, _ = prepare_request(request)
    # the base fit resolves `auto` itself (it may read smooth inputs as cubics); the search then goes
    # on with what it chose, so no refit chooses again
    fit_req = FitRequest(model=request.model, experiments=request.experiments, method=request.method,
                         options=request.options.model_copy(update={"input_interpolation": asked}))
    tell("base_fit", "", 0)
    cpu0 = time.process_time()
    with clock.phase("base_fit"):   # always run: the budget bounds the search after it
        base = fit_model(fit_req)
    base_cpu = time.process_time() - cpu0
    reading = "cubic" if base.preprocessing is not None and base.preprocessing.input_refinement \
        else request.options.input_interpolation
    fit_req = fit_req.model_copy(update={"options": fit_req.options.model_copy(
        update={"input_interpolation": reading})})
    fit_req, base, notes = solid_ground(fit_req, base, clock, base_cpu)
    request = request.model_copy(update={"options": fit_req.options})   # finer substeps, if raised, throughout
    with clock.phase("validation"):
        base_validation = validate(request, fit_req.model, base, request.validation)
    shape, shape_note = shape_at(fit_req, base, clock)
    notes += [shape_note] if shape_note else []
    state = LoopState(request.model, fit_req, base, base_validation, opts.max_refits, clock=clock, base_cpu_s=base_cpu,
                      shape=shape, shape_fit=base)
    before = summarize(base, state.validation)
    screened_first: list[CandidateScore] = []
    why_not = ""
    for round_no in range(opts.max_terms):
        why_not = unusable_fit(state.fit)
        if why_not or not clock.allows():
            break
        tell("screening", f"round {round_no + 1}", opts.max_refits - state.refits_left)
        screening = screen_state(state, opts, state.tried)
        notes += [n for n in screening.notes if n not in notes]
        if round_no == 0:
            screened_first = public_scores(screening)
        why_not = nothing_to_refit(screening)
        accepted = not why_not and try_in_rank_order(request, state, screening, tell)
        # the screen's linearised p-value can drop a law whose refit gains much: the top few refitted
        accepted = accepted or refit_below_screen(request, state, screening, tell)
        if not accepted:
            why_not = why_not or no_confirmation(state, screening)
            break
        # what is left after the step: for the next round's shape tests and, at the end, `unexplained`
        state.shape, shape_note = shape_at(state.request, state.fit, clock)
        state.shape_fit = state.fit
        notes += [shape_note] if shape_note and shape_note not in notes else []

    if clock.exhausted:
        notes.append(f"the time budget (discovery.time_budget_s = {opts.time_budget_s:g} s) ended the search "
                     f"after {clock.cpu():.1f} s of CPU; what was found until then is reported")
        why_not = why_not or (f"search stopped by the time budget ({opts.time_budget_s:g} s) before an effect "
                              "was confirmed")
    conclusion = steps_conclusion(state.steps) if state.steps else why_not or "no significant missing effect"
    unexplained, left_note = leftover_at(state.request, state.fit, state.shape_fit, state.shape, clock)
    notes += [left_note] if left_note and left_note not in notes else []
    conclusion += f"; {unexplained.message}" if unexplained else ""
    tell("done", conclusion, opts.max_refits - state.refits_left)
    model, fit, steps = with_units(state.model, state.fit, state.steps)
    return DiscoveryResult(unexplained=unexplained, discrepancy=shape.public if shape else None,
                           conclusion=conclusion, before=before, after=summarize(state.fit, state.validation),
                           steps=steps, added_inputs=added_inputs(request, state.request),
                           rejected=state.rejected, screened=screened_first, notes=notes, model=model,
                           fit=fit, wall_time_s=clock.elapsed(), timings=clock.report(),
                           budget_exhausted=clock.exhausted,
                           ambiguous=any(s.verdict == "ambiguous" for s in state.steps))


def check_user_candidates(request: DiscoverRequest) -> None:
    """Check the user's candidates before anything is fitted.

    Parameters
    ----------
    request : DiscoverRequest
        The request; its `discovery.candidates` are checked against its model.

    Raises
    ------
    ModelDefinitionError
        When a candidate's equation is not a state, its parameter is already a name in the model, or its
        term does not compile (`discovery.candidates[i].equation` / `.parameter` / `.term`).
    """
    import casadi as ca
    model = request.model
    names = set(model.states) | set(model.inputs) | {p.name for p in model.parameters}
    env = {n: ca.SX.sym(n) for n in [*model.states, *model.inputs, *(p.name for p in model.parameters),
                                     *model.constants, "t"]}
    for i, cand in enumerate(request.discovery.candidates):
        if cand.equation not in model.states:
            raise ModelDefinitionError(f"'{cand.equation}' is not a state (states: {model.states})",
                                       f"discovery.candidates[{i}].equation")
        if cand.parameter in names:
            raise ModelDefinitionError(f"'{cand.parameter}' is already a name in the model; choose a new one",
                                       f"discovery.candidates[{i}].parameter")
        compile_expression(cand.term, env, f"discovery.candidates[{i}].term")


# --- reasons to stop ------------------------------------------------------------------------------

def unusable_fit(fit: FitResult) -> str:
    """Why a fit cannot be screened from, or "".

    Parameters
    ----------
    fit : FitResult
        The current fit.

    Returns
    -------
    str
        The reason when the fit failed or its cost is not finite; else "".
    """
    if fit.quality == "failed":
        return (f"nothing screened: the fit of the declared model failed ({fit.solver.return_status}: "
                f"{fit.message}); its residual would point at the solver, not at a missing effect — fix the fit "
                "first (initial guess, bounds, method)")
    if fit.metrics.cost is None or not np.isfinite(fit.metrics.cost):
        return "nothing screened: the fit's residual is not finite (the simulation diverged)"
    return ""


def nothing_to_refit(screening: Screening) -> str:
    """Why a screen gives nothing to refit, or "".

    Parameters
    ----------
    screening : Screening
        The screen.

    Returns
    -------
    str
        "" when some candidate is significant; else why not (nothing could be scored, or the best
        candidate's share, p-value and the Bonferroni level).
    """
    if not screening.equations_scored and not screening.outputs_scored:
        return ("nothing could be scored: no state is measured directly (the equation screen needs one) and "
                "the method is equation_error (the output screen needs a simulation); use single_shooting or "
                "multiple_shooting")
    if any(sc.significant for sc in screening.scored):
        return ""
    where = _where_scored(screening)
    if not screening.scored:
        return f"no significant missing effect: no library candidate could be scored ({where})"
    best = screening.scored[0]
    white = " the residual is already white (nothing systematic left to explain);" if screening.white else ""
    return (f"no significant missing effect:{white} scored {len(screening.scored)} candidates ({where}); the best, "
            f"{best.candidate.description}, explains {100 * best.score.explained:.1f} % of the residual variance "
            f"(p = {best.score.p_value:.2g}, Bonferroni level {_alpha(screening):.2g})")


def no_confirmation(state: LoopState, screening: Screening) -> str:
    """Why no refit confirmed a candidate, or "" when a step was added earlier.

    Parameters
    ----------
    state : LoopState
        The search so far (steps, rejected candidates, refits left).
    screening : Screening
        The last screen.

    Returns
    -------
    str
        The reason (the refit budget spent, or every significant candidate rejected), or "".
    """
    if state.steps:
        return ""
    if state.refits_left <= 0:
        return (f"no effect confirmed within the budget of refits (max_refits); {len(state.rejected)} candidate(s) "
                "rejected, see `rejected`")
    return f"no effect confirmed: {len(state.rejected)} significant candidate(s) refitted and rejected (see `rejected`)"


def _alpha(screening: Screening) -> float:
    return screening.significance / max(screening.tries, 1)


def _where_scored(screening: Screening) -> str:
    parts = []
    if screening.equations_scored:
        parts.append("equation residuals of " + ", ".join(screening.equations_scored))
    if screening.outputs_scored:
        parts.append("output residuals of " + ", ".join(screening.outputs_scored))
    return "; ".join(parts)


# --- confirming refits ----------------------------------------------------------------------------

BELOW_SCREEN_REFITS = 3   # laws refitted per round though the screen did not call them significant


def refit_below_screen(request: DiscoverRequest, state: LoopState, screening: Screening,
                       tell: Progress = _silent) -> bool:
    """Refit the best named law of each family the screen did not call significant, by its screening BIC
    drop (at least `min_bic_drop`), at most `BELOW_SCREEN_REFITS`; the refit's gates decide.

    The screen linearises at the fit without the law: a law nonlinear in its variables (radiation's T⁴)
    can screen at p = 0.04, above the Bonferroni level, and gain a BIC drop of hundreds once refitted.
    The refit's likelihood ratio is held to the screen's Bonferroni level, so a law refitted here is
    held to the same evidence as one the screen passed.

    Parameters
    ----------
    request : DiscoverRequest
        The discovery request.
    state : LoopState
        The search so far; updated with the accepted step or the rejections.
    screening : Screening
        The screen, ranked.
    tell : Progress
        Progress callback, told of every refit.

    Returns
    -------
    bool
        True when a law was added.
    """
    for sc in below_screen(screening, state.tried, request.discovery):
        if state.refits_left <= 0 or not state.clock.allows():
            return False
        if sc.candidate.family in state.tried:
            continue
        tell("refit", sc.candidate.description, request.discovery.max_refits - state.refits_left)
        if discriminate(request, state, screening, sc):
            return True
    return False


def below_screen(screening: Screening, tried: set[str], opts: DiscoveryOptions) -> list[Scored]:
    """The named laws `refit_below_screen` refits: of each family not tried, the best by screening BIC
    drop that the screen did not call significant, with the physical sign, a BIC drop of at least
    `min_bic_drop` and at least `min_explained` of the residual; at most `BELOW_SCREEN_REFITS`.

    Parameters
    ----------
    screening : Screening
        The screen.
    tried : set of str
        Families refitted already.
    opts : DiscoveryOptions
        The discovery options.

    Returns
    -------
    list of Scored
        Largest screening BIC drop first.
    """
    best: dict[str, Scored] = {}
    for sc in screening.scored:
        c = sc.candidate
        if (sc.significant or c.catch_all or c.refit_only or c.family in tried
                or sc.score.bic_drop < opts.min_bic_drop or sc.score.explained < opts.min_explained
                or not (c.sign == 0 or np.sign(sc.score.beta) == np.sign(c.sign))):
            continue
        if c.family not in best or sc.score.bic_drop > best[c.family].score.bic_drop:
            best[c.family] = sc
    return sorted(best.values(), key=lambda x: -x.score.bic_drop)[:BELOW_SCREEN_REFITS]


def try_in_rank_order(request: DiscoverRequest, state: LoopState, screening: Screening,
                      tell: Progress = _silent) -> bool:
    """Refit significant candidates best first, each beside its contenders (`discriminate`), until one
    is added or the budget is spent.

    Parameters
    ----------
    request : DiscoverRequest
        The discovery request.
    state : LoopState
        The search so far; updated with the accepted step or the rejections.
    screening : Screening
        The screen, ranked.
    tell : Progress
        Progress callback, told of every refit.

    Returns
    -------
    bool
        True when a candidate was added.
    """
    for sc in [s for s in screening.scored if s.significant]:
        if sc.candidate.family in state.tried:
            continue
        held = CATCH_ALL_RESERVE if catch_all_waits(screening, sc, state) else 0
        if state.refits_left - held <= 0 or not state.clock.allows():
            if held and state.clock.allows():
                continue   # the refits left are the waiting catch-all's
            return False
        tell("refit", sc.candidate.description, request.discovery.max_refits - state.refits_left)
        state.refits_left -= held   # this law and its contenders refit within what the reserve leaves
        try:
            if discriminate(request, state, screening, sc):
                return True
        finally:
            state.refits_left += held
    return False


CATCH_ALL_RESERVE = 6   # refits kept for a waiting catch-all (its round: two variants and contenders each)


def catch_all_waits(screening: Screening, sc: Scored, state: LoopState) -> bool:
    """Whether `sc` is a named law behind which a significant catch-all, not yet tried, explains more of
    the residual: the law (with its contenders) then refits within all but `CATCH_ALL_RESERVE` refits.

    Named laws go first and catch-alls join only a round no named law leads; but when every named law
    is rejected in turn, the refit budget was spent before the catch-all was refitted: a gain drifting
    30 % over the record, its drift explaining 92 % of the residual, went unrefitted behind laws
    explaining a quarter each. The catch-all so reached is judged as any other (what it lines up with
    is refitted beside it, `catch_all`).

    Parameters
    ----------
    screening : Screening
        The screen, ranked.
    sc : Scored
        The candidate about to be refitted.
    state : LoopState
        The search so far (families tried).

    Returns
    -------
    bool
        True when `sc` is a named law and such a catch-all waits.
    """
    if sc.candidate.catch_all:
        return False
    return any(o.significant and o.candidate.catch_all and o.candidate.family not in state.tried
               and o.score.explained > sc.score.explained for o in screening.scored)
