"""Confirming refits: a screened candidate is added and the whole model refitted with the requested
method. It is kept if the refit converges, its BIC falls by `min_bic_drop`, the new parameter has
|value|/stderr ≥ `min_t_value` (where only that gate fails, its profile-likelihood interval decides:
`profile_decides`), and the validation records do not get worse (time laws on, on a validation record
that continues the estimation record in time: `off_on_validation`).

Refits start one Gauss-Newton step away from the old fit (`warm_start`), are capped at
`REFIT_MAX_ITER` Ipopt iterations, a contender's at a multiple of its leader's (`budget.RefitLimits`),
and in CPU time at what is left of the request's time budget and a multiple of the base fit's
(`budget.refit_cpu_cap`, a safety net). A smoothed
switch (Coulomb friction's tanh(v/ε)) is refitted at its widest significant width first, the
cheapest and most robust refit, and its width then refined by a score test at the refitted model,
where the linearisation is accurate (`revise.refine_width`). A delay's refits walk along the lag
(`walk_lags`). Every refit is set up by `refit_request`, counted and run by `counted_refit`, and its
validation records simulated by `timed_validation`; a kept refit becomes a step in `revise.accept`.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from greyfit.schemas.discovery import (
    DiscoverRequest,
    DiscoveryOptions,
    DiscoveryStep,
    RejectedCandidate,
    ValidationSummary,
)
from greyfit.schemas.fit import FitRequest, FitResult
from greyfit.schemas.model import Model
from greyfit.solvers.discovery.budget import Clock, RefitCost, RefitLimits, refit_cpu_cap
from greyfit.solvers.discovery.refit_test import refit_likelihood_ratio
from greyfit.solvers.discovery.shape import ShapeResult
from greyfit.solvers.discovery.summary import equation_names, validate
from greyfit.solvers.discovery.warm_start import gauss_newton_start, start_is_sound
from greyfit.solvers.dynamics.integration import integrator_of
from greyfit.solvers.errors import FitError
from greyfit.solvers.fit import fit_model
from greyfit.solvers.methods.multistart import CPU_STATUSES
from greyfit.solvers.methods.registry import simulates_outputs
from greyfit.solvers.screening.effects import Candidate
from greyfit.solvers.screening.scoring_outputs import OutputScorer
from greyfit.solvers.screening.screening import Scored, Screening, screen


@dataclass
class LoopState:
    model: Model
    request: FitRequest
    fit: FitResult
    validation: ValidationSummary | None
    refits_left: int
    steps: list[DiscoveryStep] = field(default_factory=list)
    accepted: list[Candidate] = field(default_factory=list)   # the candidate behind each step
    rejected: list[RejectedCandidate] = field(default_factory=list)
    tried: set[str] = field(default_factory=set)
    clock: Clock = field(default_factory=lambda: Clock(float("inf")))
    record_params: set[str] = field(default_factory=set)   # parameters of record-specific steps (off on validation)
    time_params: set[str] = field(default_factory=set)     # ... of those, the laws of t (carried on a continuation)
    scorer_at: tuple[FitResult, OutputScorer] | None = None   # the output scorer built at a fit, for reuse
    base_cpu_s: float = 0.0    # CPU seconds of the declared model's fit (the refits' CPU safety net)
    limits: RefitLimits | None = None   # while contenders are refitted: their bounds (`discriminate`)
    refit_costs: list[RefitCost] = field(default_factory=list)   # what each refit took, in order
    shape: ShapeResult | None = None          # the missing term's shape learned at `shape_fit` (`shape_test`)
    shape_fit: FitResult | None = None
    # named laws refitted at a fit and rejected on their t-value alone, with their BIC drop there: what
    # they explain a catch-all may not stand in for (`parsimony.catch_all_objection`)
    undetermined: list[tuple[FitResult, Candidate, float]] = field(default_factory=list)


def screen_state(state: LoopState, opts: DiscoveryOptions, exclude: set[str]) -> Screening:
    """Screen at the current fit, timed, reusing the output sensitivities if this fit was screened.

    Parameters
    ----------
    state : LoopState
        The search so far; its cached output scorer is reused and replaced.
    opts : DiscoveryOptions
        The discovery options.
    exclude : set of str
        Candidate families not to score.

    Returns
    -------
    Screening
        The screen (`screening.screen`).
    """
    cached = state.scorer_at[1] if state.scorer_at is not None and state.scorer_at[0] is state.fit else None
    with state.clock.phase("screening"):
        screening = screen(state.request, state.fit, opts, exclude, cached)
    if screening.output_scorer is not None:
        state.scorer_at = (state.fit, screening.output_scorer)
    return screening


REFIT_MAX_ITER = 50
# RK4 is stable for |λ|·h up to 2.8 on the real axis; the stiff part of a sharp tanh is the fast
# relaxation onto sticking, whose transient need not be accurate, only stable and damped (RK4's
# factor at λh = 1.5 is 0.27 against the exact 0.22); 0.5 ran up to 77 substeps on a 0.1 %-of-RMS
# width, a refit of minutes that did not converge. Measured on the Coulomb MSD: c within 0.15 %
# of the 4×-substep refit.
RK4_STEP_LIMIT = 1.5


POLISH_MAX_ITER = 20


def run_refit(state: LoopState, req: FitRequest) -> FitResult:
    """fit_model within the refit's bounds (`_within_budget`), timed as a refit, its cost recorded.

    A Gauss-Newton refit that runs out of iterations is polished with the exact Hessian from where
    it stopped: with a sharp tanh, Gauss-Newton reaches the answer and then crawls without meeting
    the tolerance (measured: 50 iterations and more, parameters already within 0.1 %), where Newton
    converges in 5-8. Only next to an answer, though: when the refit already lowered the BIC of the
    fit it extends; an iterate that did not has wandered off, and Newton from there is a long solve
    of nothing.

    Parameters
    ----------
    state : LoopState
        The search so far (its clock, limits and base fit's CPU time cap the refit, and it is timed;
        its `refit_costs` get the refit's iterations, CPU seconds and convergence).
    req : FitRequest
        The refit's request.

    Returns
    -------
    FitResult
        The refit, or its polished form when that did not fail or has the lower BIC.

    Raises
    ------
    FitError
        When the request's model or data do not compile or prepare (from `fit_model`).
    """
    cpu0 = time.process_time()
    with state.clock.phase("refits"):
        fit = fit_model(_within_budget(state, req))
        iterations = fit.solver.iterations
        if (fit.solver.return_status == "Maximum_Iterations_Exceeded" and req.options.hessian == "gauss_newton"
                and state.clock.left() > 0 and bic(fit) < bic(state.fit)):
            polish = req.model_copy(update={
                "model": with_estimates(req.model, fit),
                "options": req.options.model_copy(update={"hessian": "exact", "max_iter": POLISH_MAX_ITER})})
            polished = fit_model(_within_budget(state, polish))
            iterations += polished.solver.iterations
            if polished.quality != "failed" or bic(polished) < bic(fit):
                fit = polished
    state.refit_costs.append(RefitCost(iterations, time.process_time() - cpu0, fit.quality != "failed"))
    return fit


def _within_budget(state: LoopState, req: FitRequest) -> FitRequest:
    """The request with its CPU time capped by what is left of the budget and the base fit's multiple,
    and a contender's iterations and CPU time by its `state.limits`."""
    opts = req.options
    cpu = min(opts.max_cpu_time, max(state.clock.left(), 1.0), refit_cpu_cap(state.base_cpu_s))
    max_iter = opts.max_iter
    if state.limits is not None:
        cpu, max_iter = min(cpu, state.limits.max_cpu_time), min(max_iter, state.limits.max_iter)
    if cpu < opts.max_cpu_time or max_iter < opts.max_iter:
        req = req.model_copy(update={"options": opts.model_copy(update={"max_cpu_time": cpu, "max_iter": max_iter})})
    return req


def build_refit(request: DiscoverRequest, state: LoopState, sc: Scored,
                start: FitResult | None = None) -> tuple[Model, list[str], FitRequest]:
    """(augmented model with its start values, new parameter names, refit request) of a candidate.

    Parameters
    ----------
    request : DiscoverRequest
        The discovery request (its declared model, for a fresh start).
    state : LoopState
        The search so far (the current model, fit and request).
    sc : Scored
        The scored candidate.
    start : FitResult or None
        A refit of a sibling variant to start from (a neighbouring lag), instead of the current fit.

    Returns
    -------
    tuple of (Model, list of str, FitRequest)
        The model with the candidate, started at the current estimates (or the declared values, or the
        sibling's) and one Gauss-Newton step on where the step can be formed and simulates
        (`warm_start.start_is_sound`); the new parameters' names;
        the refit request with the candidate's data and capped options (`refit_options`).
    """
    c = sc.candidate
    begin = with_declared_start(state.model, request.model) if c.fresh_start else \
        with_estimates(state.model, state.fit)
    new_model, new_params = c.apply(begin)
    if start is not None:
        new_model = with_estimates(new_model, start)
    elif new_params and not c.fresh_start and not c.transform_experiments and sc.scorer is not None:
        stepped = gauss_newton_start(sc.scorer, c, state.fit, new_model, new_params)
        # a step that cannot be simulated is no start (a destabilising term blows up): the neutral one
        new_model = stepped if start_is_sound(state.request, state.fit, stepped) else new_model
    return new_model, new_params, refit_request(state, new_model, c, sc.score.beta)


def refit_request(state: LoopState, model: Model, cand: Candidate, beta: float, **options) -> FitRequest:
    """The request of a refit with `cand` in `model`: the current request with the candidate's data
    (a delayed input) and the refit's capped options (`refit_options`).

    Parameters
    ----------
    state : LoopState
        The search so far (its current request).
    model : Model
        The model to refit (with the candidate, and its start values).
    cand : Candidate
        The candidate (its `transform_experiments` and `stiffness`).
    beta : float
        The candidate's screened coefficient (for the substeps a stiff term needs).
    **options
        Further option updates (e.g. ``hessian="exact"`` for a start next to the answer).

    Returns
    -------
    FitRequest
        The refit's request.
    """
    experiments = (cand.transform_experiments(state.request.experiments) if cand.transform_experiments
                   else state.request.experiments)
    opts = refit_options(state.request, cand, beta)
    if options:
        opts = opts.model_copy(update=options)
    return state.request.model_copy(update={"model": model, "experiments": experiments, "options": opts})


def counted_refit(state: LoopState, req: FitRequest) -> FitResult | str:
    """One refit counted against `max_refits` and run within the budget (`run_refit`).

    Parameters
    ----------
    state : LoopState
        The search so far; its refits left are counted down.
    req : FitRequest
        The refit's request.

    Returns
    -------
    FitResult or str
        The refit; or, when the model or data do not compile or the solver raised, the error's text (a
        term the solver cannot handle is a rejection, not a crash).
    """
    state.refits_left -= 1
    try:
        return run_refit(state, req)
    except (FitError, RuntimeError, ValueError) as exc:
        return str(exc)


def timed_validation(request: DiscoverRequest, state: LoopState, model: Model, fit: FitResult,
                     experiments=None, neutral: set[str] | None = None,
                     fitted_with: FitRequest | None = None) -> ValidationSummary | None:
    """A model on the validation records, timed as validation.

    Parameters
    ----------
    request : DiscoverRequest
        The discovery request (its validation records, unless `experiments` are given).
    state : LoopState
        The search so far (its clock times the simulation).
    model : Model
        The model.
    fit : FitResult
        Its fit.
    experiments : list of Experiment or None
        The records to simulate (the validation records with a candidate's data); None: the request's.
    neutral : set of str or None
        Parameters switched off there (record-specific terms); None: those of the steps so far
        (`off_on_validation`).
    fitted_with : FitRequest or None
        The request the model was fitted with (None: the search's current one): its RK4 substeps,
        raised for a stiff term, simulate the validation records too. With the request's own, a
        narrow tanh of Coulomb friction was simulated coarsely there and a better width refused.

    Returns
    -------
    ValidationSummary or None
        Its validation metrics; None without validation records or when they cannot be simulated.
    """
    exps = request.validation if experiments is None else experiments
    off = off_on_validation(request, state, set()) if neutral is None else neutral
    substeps = (fitted_with or state.request).options.substeps
    if substeps > request.options.substeps:
        request = request.model_copy(update={"options": request.options.model_copy(update={"substeps": substeps})})
    with state.clock.phase("validation"):
        return validate(request, model, fit, exps, off)


def continues_in_time(request: DiscoverRequest) -> bool:
    """Whether every validation record continues the estimation records in time (starts where they end).

    Parameters
    ----------
    request : DiscoverRequest
        The discovery request.

    Returns
    -------
    bool
        True when there are validation records and each starts no earlier than the last estimation
        sample (less one sample interval): a law of t fitted on the estimation record holds there.
    """
    if not request.validation or not request.experiments:
        return False
    end = max(float(e.time[-1]) for e in request.experiments)
    dt = min(float(np.median(np.diff(e.time))) for e in request.experiments if len(e.time) > 1)
    return all(float(v.time[0]) >= end - dt for v in request.validation)


def off_on_validation(request: DiscoverRequest, state: LoopState, new: set[str], new_in_time: bool = False) -> set[str]:
    """Parameters switched off on the validation records: those of record-specific terms, except the
    laws of t when the validation records continue the estimation records in time (a drift goes on).

    Parameters
    ----------
    request : DiscoverRequest
        The discovery request (its records' times).
    state : LoopState
        The search so far (the record-specific and time-law parameters of its steps).
    new : set of str
        A candidate's record-specific parameters, beside the steps'.
    new_in_time : bool
        Whether those are a law of t.

    Returns
    -------
    set of str
        The parameters set to 0 on the validation records.
    """
    off = state.record_params | new
    if continues_in_time(request):
        off = off - state.time_params - (new if new_in_time else set())
    return off


@dataclass
class Refitted:
    """A candidate refitted: past the evidence gates (BIC, whitened likelihood ratio, t-value), or not (`rejection`)."""

    sc: Scored
    fit: FitResult
    model: Model
    params: list[str]
    request: FitRequest
    t_value: float | None
    bic_drop: float
    order: int | None
    lr_p: float | None
    validation: ValidationSummary | None = None
    rejection: RejectedCandidate | None = None   # set when the refit converged but failed an evidence gate
    only_t: bool = False   # that rejection was on the t-value alone (the BIC drop and likelihood ratio passed)
    profiled: str = ""     # kept on its profile-likelihood interval though its t-value was below the gate


def refit_candidate(request: DiscoverRequest, state: LoopState, variants: list[Scored],
                    screening: Screening) -> Refitted | RejectedCandidate:
    """Refit with the candidate (the best of its variants) and apply the evidence gates; the
    validation records are simulated but not yet judged (`discriminate` compares contenders).

    Parameters
    ----------
    request : DiscoverRequest
        The discovery request (options, declared model, validation experiments).
    state : LoopState
        The search so far (model, request, fit, steps, refits left, budget).
        Its refits left are counted down.
    variants : list of Scored
        The candidate's variants to refit (`discriminate.variants_of`); the best refit is judged.
    screening : Screening
        The screen the candidate came from.

    Returns
    -------
    Refitted or RejectedCandidate
        The refit with its evidence and validation; the refit with its `rejection` set when it converged
        but an evidence gate ("evidence") failed; or why it was rejected without a usable refit
        ("refit_error", "cpu_limit", "solver_failed").
    """
    opts = request.discovery
    errors: list[str] = []
    done = [r for r in (_refit_variant(request, state, sc, errors) for sc in variants
                        if state.refits_left > 0 and state.clock.allows()) if r is not None]
    if done and variants[0].candidate.lag > 0:
        done += walk_lags(request, state, screening, done, errors)
    best = max(done, key=lambda r: _rank_refit(r[1])) if done else None
    head = variants[0].candidate
    where = equation_names(screening, head)
    if best is None:
        why = "no refit within the budget (max_refits or discovery.time_budget_s)"
        return RejectedCandidate(effect=head.effect, equation=where, term=head.term, reason="refit_error",
                                 detail="; ".join(errors)[:2000] or why)
    sc, new_fit, new_model, new_params, new_req = best
    c = sc.candidate
    status = new_fit.solver.return_status
    if status in CPU_STATUSES:
        return RejectedCandidate(effect=c.effect, equation=where, term=c.term, reason="cpu_limit",
                                 detail="not decided: the refit stopped at its CPU time limit before converging "
                                        f"({_cpu_cap_text(state)}): no verdict on the evidence")
    if new_fit.quality == "failed":   # "suspect" is fine here: what is left may be the next effect
        cut = (f"; {state.limits.reason}" if state.limits is not None and status == "Maximum_Iterations_Exceeded"
               else "")
        return RejectedCandidate(effect=c.effect, equation=where, term=c.term, reason="solver_failed",
                                 detail=f"not decided: the refit did not converge ({status}, "
                                        f"{new_fit.solver.iterations} iterations{cut}): no verdict on the evidence")
    t_value = t_value_of(new_fit, new_params)
    bic_drop = bic(state.fit) - bic(new_fit)
    order, lr_p = refit_likelihood_ratio(state.request, state.fit, new_req, new_fit)
    level = screening.significance / max(screening.tries, 1) / c.multiplicity
    bic_or_lr_fails = bic_drop < opts.min_bic_drop or (lr_p is not None and lr_p >= level)
    t_fails = t_value is not None and t_value < opts.min_t_value
    profiled = ""
    if t_fails and not bic_or_lr_fails:   # the likelihood confirms it and one gate does not: its profile decides
        profiled = profile_decides(state, new_req, new_fit, new_params, level)
        t_fails = not profiled
    if bic_or_lr_fails or t_fails:
        t_text = "n/a" if t_value is None else f"{t_value:.1f}"
        lr_text = "" if lr_p is None else \
            f", likelihood ratio p = {lr_p:.2g} with an AR({order}) noise model (needs {level:.2g})"
        # the refit is kept beside its rejection: as a runner-up it is compared by BIC too
        return Refitted(sc, new_fit, new_model, new_params, new_req, t_value, bic_drop, order, lr_p, rejection=(
            RejectedCandidate(effect=c.effect, equation=where, term=c.term, reason="evidence",
                              detail=f"the refit did not confirm it: BIC drop {bic_drop:.1f} (needs "
                                     f"{opts.min_bic_drop:g}){lr_text}, t = {t_text} (needs {opts.min_t_value:g})")),
            only_t=not bic_or_lr_fails)
    out = Refitted(sc, new_fit, new_model, new_params, new_req, t_value, bic_drop, order, lr_p, profiled=profiled)
    out.validation = validate_refit(request, state, out)
    return out


PROFILE_LEVEL_CAP = 0.9999   # the profile's confidence level: the refit's Bonferroni level, at most this


def profile_decides(state: LoopState, req: FitRequest, fit: FitResult, names: list[str], level: float) -> str:
    """Whether the profile-likelihood interval of every new coefficient excludes 0, at the refit's level.

    A t-value is a quadratic reading of the cost: where the new coefficient is nearly collinear with
    declared ones, or the HAC standard error is inflated by strong colour, it can stay below the gate
    while the BIC and the whitened likelihood ratio confirm the law (EMPS's Coulomb friction: BIC drop
    2 887, t = 1.8). The profile follows the cost itself, every other parameter re-optimised, with its
    threshold scaled for coloured residuals as the fit's profiles are.

    Parameters
    ----------
    state : LoopState
        The search so far (the profile refit is counted and bounded as a refit).
    req : FitRequest
        The refit's request.
    fit : FitResult
        The refit.
    names : list of str
        The new coefficients.
    level : float
        The refit's significance level (Bonferroni): the interval's confidence is 1 − level (at most
        `PROFILE_LEVEL_CAP`).

    Returns
    -------
    str
        "" when an interval reaches 0, is open or was not computed; else a note with the intervals.
    """
    if not names or state.refits_left <= 0 or not state.clock.allows():
        return ""
    confidence = min(max(1.0 - level, 0.95), PROFILE_LEVEL_CAP)
    preq = req.model_copy(update={"model": with_estimates(req.model, fit), "options": req.options.model_copy(
        update={"profile": list(names), "confidence_level": confidence})})
    pfit = counted_refit(state, preq)
    if isinstance(pfit, str) or pfit.quality == "failed" or not pfit.profile:
        return ""
    shown = []
    for n in names:
        iv = pfit.profile.get(n)
        if iv is None or iv.lower is None or iv.upper is None or iv.lower * iv.upper <= 0:
            return ""
        shown.append(f"{n} in [{iv.lower:.4g}, {iv.upper:.4g}]")
    return (f"its t-value is below the gate, but the profile likelihood at {100 * confidence:.4g} % excludes 0: "
            + ", ".join(shown))


def _cpu_cap_text(state: LoopState) -> str:
    parts = [f"at most {refit_cpu_cap(state.base_cpu_s):.3g} s, a multiple of the base fit's, and what was left of "
             "discovery.time_budget_s"]
    if state.limits is not None:
        parts.append(state.limits.reason)
    return "; ".join(parts)


VariantRefit = tuple[Scored, FitResult, Model, list[str], FitRequest]
WALK_MAX_REFITS = 6   # a delay's refits beyond the screen's two


def _refit_variant(request: DiscoverRequest, state: LoopState, sc: Scored, errors: list[str],
                   start: FitResult | None = None) -> VariantRefit | None:
    new_model, new_params, new_req = build_refit(request, state, sc, start)
    new_fit = counted_refit(state, new_req)
    if isinstance(new_fit, str):
        errors.append(new_fit)
        return None
    return sc, new_fit, new_model, new_params, new_req


def walk_lags(request: DiscoverRequest, state: LoopState, screening: Screening, done: list[VariantRefit],
              errors: list[str]) -> list[VariantRefit]:
    """Refits of a delay at the lags next to the best refitted one, while that one has an untried
    neighbour: the refit cost, not the screen, picks the lag.

    The screen linearises the delayed input's effect at the fit without it, whose lags have already
    stretched to mimic the delay; it then ranks short lags first (a two-lag process delayed by 4
    samples: the screen's best was 1, its second 2). The refit cost along the lag has one minimum
    near the true one, so a walk from the screen's best to the lag whose two neighbours both refit
    worse finds it, each refit started from its neighbour's.

    Parameters
    ----------
    request : DiscoverRequest
        The discovery request (options, declared model, validation experiments).
    state : LoopState
        The search so far (its refits left are counted down, its clock bounds the walk).
    screening : Screening
        The screen the candidate came from (it holds every lag of the family).
    done : list of VariantRefit
        The refits of the screen's variants, (scored, fit, model, new parameters, request) each.
    errors : list of str
        Appended: the errors of refits that could not run.

    Returns
    -------
    list of VariantRefit
        The walk's refits (at most `WALK_MAX_REFITS`).
    """
    head = done[0][0]
    by_lag = {s.candidate.lag: s for s in screening.scored
              if s.candidate.family == head.candidate.family and s.scored_on == head.scored_on}
    tried = {r[0].candidate.lag for r in done}
    walked: list[VariantRefit] = []
    while len(walked) < WALK_MAX_REFITS and state.refits_left > 0 and state.clock.allows():
        best = max([*done, *walked], key=lambda r: _rank_refit(r[1]))
        lag = best[0].candidate.lag
        nxt = [k for k in (lag + 1, lag - 1) if k in by_lag and k not in tried]
        if not nxt:
            break
        tried.add(nxt[0])
        r = _refit_variant(request, state, by_lag[nxt[0]], errors, start=best[1])
        if r is not None:
            walked.append(r)
    return walked


def validate_refit(request: DiscoverRequest, state: LoopState, r: Refitted) -> ValidationSummary | None:
    """The refitted model on the validation records, with the record-specific terms (steps, drifts in
    the estimation record's time) switched off: their clock does not carry over to new data.

    Parameters
    ----------
    request : DiscoverRequest
        The discovery request (options, declared model, validation experiments).
    state : LoopState
        The search so far (model, request, fit, steps, refits left, budget).
    r : Refitted
        The refitted candidate.

    Returns
    -------
    ValidationSummary or None
        Its validation metrics; None without validation records or when they cannot be simulated.
    """
    c = r.sc.candidate
    exps = request.validation
    for prior in [*state.accepted, c]:   # inputs added by earlier steps (a delayed input), then this one's
        if prior.transform_experiments and exps:
            exps = prior.transform_experiments(exps)
    neutral = off_on_validation(request, state, set(r.params) if c.record_specific else set(), "t" in c.variables)
    return timed_validation(request, state, r.model, r.fit, exps, neutral, r.request)


def bic(fit: FitResult) -> float:
    """A fit's BIC, infinite where it has none.

    Parameters
    ----------
    fit : FitResult
        The fit.

    Returns
    -------
    float
        `fit.metrics.bic`, or inf when it is None.
    """
    return float("inf") if fit.metrics.bic is None else fit.metrics.bic


def _rank_refit(fit: FitResult) -> tuple[bool, float]:
    return fit.quality != "failed", -bic(fit)


def with_declared_start(model: Model, declared: Model) -> Model:
    """The model with the user's initial values for the declared parameters (a fresh start).

    Parameters
    ----------
    model : Model
        The model (possibly augmented).
    declared : Model
        The user's declared model.

    Returns
    -------
    Model
        A copy whose parameters declared in `declared` start at their declared values; the others unchanged.
    """
    start = {p.name: p.value for p in declared.parameters}
    return model.model_copy(update={"parameters": [p.model_copy(update={"value": start.get(p.name, p.value)})
                                                   for p in model.parameters]})


def refit_options(req: FitRequest, cand: Candidate, beta: float):
    """A confirming refit starts next to its answer: a real effect converges in a few dozen iterations,
    so the budget is capped (one that does not is reported as not converged, not as evidence).
    More RK4 substeps when the new term is stiff (a sharp tanh): |λ|·h ≤ RK4_STEP_LIMIT.

    Parameters
    ----------
    req : FitRequest
        The current fit's request.
    cand : Candidate
        The candidate (its `stiffness` per unit coefficient).
    beta : float
        The candidate's screened coefficient.

    Returns
    -------
    FitOptions
        The options with `max_iter` capped at `REFIT_MAX_ITER` and, for a simulating method with a
        fixed-step integrator and a stiff term, `substeps` raised (at most 100).
    """
    opts = req.options.model_copy(update={"max_iter": min(req.options.max_iter, REFIT_MAX_ITER)})
    if not simulates_outputs(req.method) or not integrator_of(opts).fixed_step or cand.stiffness == 0:
        return opts
    rate = abs(beta) * cand.stiffness
    dt = max(float(np.max(np.diff(e.time))) for e in req.experiments)
    need = int(np.ceil(rate * dt / RK4_STEP_LIMIT))
    if need <= opts.substeps:
        return opts
    return opts.model_copy(update={"substeps": min(need, 100)})


def with_estimates(model: Model, fit: FitResult) -> Model:
    """The model with its parameters' initial values set to the fitted ones (inside the bounds).

    Parameters
    ----------
    model : Model
        The model.
    fit : FitResult
        A fit of it (per-experiment parameters keep their declared start).

    Returns
    -------
    Model
        A copy with the initial values set and clipped to the bounds.
    """
    params = []
    for p in model.parameters:
        est = fit.parameters.get(p.name)
        value = p.value if est is None or p.per_experiment else est.value
        lo = -np.inf if p.lower is None else p.lower
        hi = np.inf if p.upper is None else p.upper
        params.append(p.model_copy(update={"value": float(np.clip(value, lo, hi))}))
    return model.model_copy(update={"parameters": params})


def t_value_of(fit: FitResult, names: list[str]) -> float | None:
    """The smallest |value|/stderr among some parameters.

    Parameters
    ----------
    fit : FitResult
        The fit.
    names : list of str
        The parameters' names (all must be in the fit).

    Returns
    -------
    float or None
        The smallest t-value; None without names or when one has no (or a zero) standard error.
    """
    if not names:
        return None
    vals = []
    for n in names:
        p = fit.parameters[n]
        if p.stderr is None or p.stderr == 0:
            return None
        vals.append(abs(p.value) / p.stderr)
    return min(vals)
