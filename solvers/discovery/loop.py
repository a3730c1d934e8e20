"""Close the loop: fit, trace the residual to a named missing effect, add it, refit, report.

The steps, in the order they run:

1. Fit the declared model with the requested method (`fit_model`); simulate it on the validation
   experiments, if any.
2. Screen (`screening.screen`): every candidate of the effect library is scored
   - on the equation residuals of measured states (`scoring_equations`), and
   - on the output residuals through the output sensitivities (`scoring_outputs`): effects in
     equations of unmeasured states and in the output path (`output_effects`) show there.
   A candidate is significant when its F-test p-value is below `significance` divided by the number
   of candidates tried (Bonferroni), it explains at least `min_explained` of the residual variance,
   and its sign is physical. One ranking: largest BIC drop first, a change in time (step, drift)
   behind a structural effect that explains nearly as much.
3. Confirm (`confirm_candidate`): the best significant candidate is added and the whole model
   refitted with the requested method, warm-started. It is kept if the refit converges, its BIC falls
   by `min_bic_drop`, the new parameter has |value|/stderr ≥ `min_t_value`, and the validation
   records do not get worse. Otherwise it is recorded in `rejected` with the reason and the next
   ranked candidate is tried, within `max_refits` refits.
4. Repeat up to `max_terms`; report before/after (estimation and validation), each step's evidence
   and the augmented model. When nothing is added, the conclusion says why.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from schemas.discovery import (
    CandidateScore, DiscoverRequest, DiscoveryResult, DiscoveryStep, Evidence, FitSummary, NewParameter,
    RejectedCandidate, ValidationSummary,
)
from schemas.fit import FitRequest, FitResult
from schemas.model import Model
from solvers.discovery.effects import Candidate
from solvers.discovery.screening import Scored, Screening, screen
from solvers.errors import FitError, ModelDefinitionError
from solvers.expressions import compile_expression
from solvers.fit import fit_model
from solvers.preprocess import prepare_request


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


def discover(request: DiscoverRequest) -> DiscoveryResult:
    """Fit, find and add missing effects, refit; see the module docstring for the tests used."""
    started = time.perf_counter()
    opts = request.discovery
    check_user_candidates(request)
    # detrend/decimate/window once, for the fits and the screens alike
    request, _ = prepare_request(request)
    fit_req = FitRequest(model=request.model, experiments=request.experiments, method=request.method,
                         options=request.options)
    base = fit_model(fit_req)
    state = LoopState(request.model, fit_req, base, validate(request, fit_req.model, base, fit_req.experiments),
                      opts.max_refits)
    before = summarize(base, state.validation)
    screened_first: list[CandidateScore] = []
    notes: list[str] = []
    why_not = ""
    for round_no in range(opts.max_terms):
        why_not = unusable_fit(state.fit)
        if why_not:
            break
        screening = screen(state.request, state.fit, opts, state.tried)
        notes += [n for n in screening.notes if n not in notes]
        if round_no == 0:
            screened_first = public_scores(screening)
        why_not = nothing_to_refit(screening)
        if why_not:
            break
        accepted = try_in_rank_order(request, state, screening)
        if not accepted:
            why_not = no_confirmation(state, screening)
            break

    conclusion = ("added " + "; ".join(f"{s.effect} ({s.description})" for s in state.steps) if state.steps
                  else why_not or "no significant missing effect")
    return DiscoveryResult(conclusion=conclusion, before=before, after=summarize(state.fit, state.validation),
                           steps=state.steps, added_inputs=added_inputs(request, state.request),
                           rejected=state.rejected, screened=screened_first, notes=notes, model=state.model,
                           fit=state.fit, wall_time_s=time.perf_counter() - started)


def check_user_candidates(request: DiscoverRequest) -> None:
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
    if fit.quality == "failed":
        return (f"nothing screened: the fit of the declared model failed ({fit.solver.return_status}: "
                f"{fit.message}); its residual would point at the solver, not at a missing effect — fix the fit "
                "first (initial guess, bounds, method)")
    if fit.metrics.cost is None or not np.isfinite(fit.metrics.cost):
        return "nothing screened: the fit's residual is not finite (the simulation diverged)"
    return ""


def nothing_to_refit(screening: Screening) -> str:
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

def try_in_rank_order(request: DiscoverRequest, state: LoopState, screening: Screening) -> bool:
    """Refit significant candidates best first until one is confirmed or the budget is spent."""
    tried_now: set[str] = set()
    for sc in [s for s in screening.scored if s.significant]:
        fam = sc.candidate.family
        if fam in tried_now or fam in state.tried:
            continue
        if state.refits_left <= 0:
            return False
        tried_now.add(fam)
        variants = ([s for s in screening.scored if s.significant and s.candidate.family == fam
                     and s.scored_on == sc.scored_on][:2] if sc.candidate.refit_variants else [sc])
        verdict = confirm_candidate(request, state, variants, screening)
        if verdict is None:
            state.tried.add(fam)
            return True
        state.rejected.append(verdict)
        state.tried.add(fam)
    return False


def confirm_candidate(request: DiscoverRequest, state: LoopState, variants: list[Scored],
                      screening: Screening) -> RejectedCandidate | None:
    """Refit with the candidate (the best of its variants); None when kept, else why it was not."""
    opts = request.discovery
    best = None
    errors = []
    for sc in variants:
        if state.refits_left <= 0:
            break
        c = sc.candidate
        start = with_declared_start(state.model, request.model) if c.fresh_start else \
            with_estimates(state.model, state.fit)
        new_model, new_params = c.apply(start)
        experiments = (c.transform_experiments(state.request.experiments) if c.transform_experiments
                       else state.request.experiments)
        new_req = state.request.model_copy(update={"model": new_model, "experiments": experiments,
                                                   "options": refit_options(state.request, c, sc.score.beta)})
        state.refits_left -= 1
        try:
            new_fit = fit_model(new_req)
        except (FitError, RuntimeError, ValueError) as exc:   # a term the solver cannot handle is rejected
            errors.append(str(exc))
            continue
        if best is None or _rank_refit(new_fit) > _rank_refit(best[1]):
            best = (sc, new_fit, new_model, new_params, new_req)
    head = variants[0].candidate
    where = _equation_names(screening, head)
    if best is None:
        return RejectedCandidate(effect=head.effect, equation=where, term=head.term, reason="refit_error",
                                 detail="; ".join(errors)[:2000] or "no refit within the budget")
    sc, new_fit, new_model, new_params, new_req = best
    c = sc.candidate
    status = new_fit.solver.return_status
    if status == "Maximum_CpuTime_Exceeded":
        return RejectedCandidate(effect=c.effect, equation=where, term=c.term, reason="cpu_limit",
                                 detail=f"the refit stopped at max_cpu_time ({new_req.options.max_cpu_time} s) "
                                        "before converging: no verdict on the evidence; raise options.max_cpu_time")
    if new_fit.quality == "failed":   # "suspect" is fine here: what is left may be the next effect
        return RejectedCandidate(effect=c.effect, equation=where, term=c.term, reason="solver_failed",
                                 detail=f"the refit did not converge ({status}, {new_fit.solver.iterations} "
                                        "iterations): no verdict on the evidence")
    t_value = _t_value(new_fit, new_params)
    bic_drop = _bic(state.fit) - _bic(new_fit)
    if bic_drop < opts.min_bic_drop or (t_value is not None and t_value < opts.min_t_value):
        t_text = "n/a" if t_value is None else f"{t_value:.1f}"
        return RejectedCandidate(effect=c.effect, equation=where, term=c.term, reason="evidence",
                                 detail=f"the refit did not confirm it: BIC drop {bic_drop:.1f} (needs "
                                        f"{opts.min_bic_drop:g}), t = {t_text} (needs {opts.min_t_value:g})")
    validation_exps = (c.transform_experiments(request.validation) if c.transform_experiments and request.validation
                       else request.validation)
    new_validation = validate(request, new_model, new_fit, validation_exps)
    worse = _validation_worse(state.validation, new_validation, opts.validation_tolerance)
    if worse:
        return RejectedCandidate(effect=c.effect, equation=where, term=c.term, reason="validation",
                                 detail=f"better on the estimation data (BIC -{bic_drop:.0f}) but worse on the "
                                        f"validation records: {worse}")
    state.steps.append(DiscoveryStep(
        effect=c.effect, equation=where, term=c.term, description=c.description,
        parameters=[NewParameter(name=n, value=new_fit.parameters[n].value, stderr=new_fit.parameters[n].stderr,
                                 ci95=new_fit.parameters[n].ci95) for n in new_params],
        evidence=Evidence(scored_on=sc.scored_on, explained_variance=sc.score.explained,
                          screening_bic_drop=sc.score.bic_drop, p_value=sc.score.p_value,
                          bic_before=state.fit.metrics.bic, bic_after=new_fit.metrics.bic, bic_drop=bic_drop,
                          t_value=t_value, residual_correlation_before=sc.score.corr_before,
                          residual_correlation_after=_correlation_after(sc, new_req, new_fit, screening)),
        after=summarize(new_fit, new_validation), record_specific=c.record_specific))
    state.accepted.append(c)
    # no steps of a step, no drift of a drift
    state.tried.update(f"{kind}:{n}" for n in new_params for kind in ("parameter_step", "parameter_drift"))
    state.model, state.fit, state.request, state.validation = new_model, new_fit, new_req, new_validation
    drop_superseded(request, state)
    return None


def drop_superseded(request: DiscoverRequest, state: LoopState) -> None:
    """An earlier step whose parameter lost its evidence once a later effect came in is dropped,
    when the model without it is as good (BIC within `min_bic_drop`): e.g. a stiffness that switches
    with |y|, taken first, and then a cubic spring that explains it properly."""
    opts = request.discovery
    if any(c.transform_experiments for c in state.accepted):
        return   # the data were rewritten for a delayed input: no replay
    for idx in reversed(range(len(state.steps) - 1)):
        step = state.steps[idx]
        names = [p.name for p in step.parameters]
        t_value = _t_value(state.fit, names) if all(n in state.fit.parameters for n in names) else None
        if not names or t_value is None or t_value >= opts.min_t_value or state.refits_left <= 0:
            continue
        model = request.model
        for k, c in enumerate(state.accepted):
            if k != idx:
                model, _ = c.apply(model)
        model = with_estimates(model, state.fit)
        new_req = state.request.model_copy(update={"model": model})
        state.refits_left -= 1
        try:
            new_fit = fit_model(new_req)
        except (FitError, RuntimeError, ValueError):
            continue
        if new_fit.quality == "failed" or _bic(new_fit) > _bic(state.fit) + opts.min_bic_drop:
            continue
        state.rejected.append(RejectedCandidate(
            effect=step.effect, equation=step.equation, term=step.term, reason="superseded",
            detail=f"kept at first; after the effects added later its parameter has t = {t_value:.1f} and the "
                   f"model without it is as good (BIC {state.fit.metrics.bic:.1f} -> {new_fit.metrics.bic:.1f})"))
        del state.steps[idx]
        del state.accepted[idx]
        state.model, state.fit, state.request = model, new_fit, new_req
        state.validation = validate(request, model, new_fit, request.validation)


def _bic(fit: FitResult) -> float:
    return float("inf") if fit.metrics.bic is None else fit.metrics.bic


def _rank_refit(fit: FitResult) -> tuple[bool, float]:
    return fit.quality != "failed", -_bic(fit)


def with_declared_start(model: Model, declared: Model) -> Model:
    """The model with the user's initial values for the declared parameters (a fresh start)."""
    start = {p.name: p.value for p in declared.parameters}
    return model.model_copy(update={"parameters": [p.model_copy(update={"value": start.get(p.name, p.value)})
                                                   for p in model.parameters]})


REFIT_MAX_ITER = 50


def refit_options(req: FitRequest, cand: Candidate, beta: float):
    """A confirming refit starts next to its answer: a real effect converges in a few dozen iterations,
    so the budget is capped (one that does not is reported as not converged, not as evidence).
    More RK4 substeps when the new term is stiff (a sharp tanh): |λ|·h ≤ 0.5 keeps RK4 accurate."""
    opts = req.options.model_copy(update={"max_iter": min(req.options.max_iter, REFIT_MAX_ITER)})
    if req.method.value == "equation_error" or opts.integrator != "rk4" or cand.stiffness == 0:
        return opts
    rate = abs(beta) * cand.stiffness
    dt = max(float(np.max(np.diff(e.time))) for e in req.experiments)
    need = int(np.ceil(2 * rate * dt))
    if need <= opts.substeps:
        return opts
    return opts.model_copy(update={"substeps": min(need, 100)})


def with_estimates(model: Model, fit: FitResult) -> Model:
    """The model with its parameters' initial values set to the fitted ones (inside the bounds)."""
    params = []
    for p in model.parameters:
        est = fit.parameters.get(p.name)
        value = p.value if est is None or p.per_experiment else est.value
        lo = -np.inf if p.lower is None else p.lower
        hi = np.inf if p.upper is None else p.upper
        params.append(p.model_copy(update={"value": float(np.clip(value, lo, hi))}))
    return model.model_copy(update={"parameters": params})


def _t_value(fit: FitResult, names: list[str]) -> float | None:
    if not names:
        return None
    vals = []
    for n in names:
        p = fit.parameters[n]
        if p.stderr is None or p.stderr == 0:
            return None
        vals.append(abs(p.value) / p.stderr)
    return min(vals)


def _correlation_after(sc: Scored, new_req: FitRequest, new_fit: FitResult, screening: Screening) -> float:
    """Correlation of the refitted model's residual with the candidate's column (was: corr_before)."""
    try:
        if sc.scored_on == "outputs" and screening.output_scorer is not None:
            old = screening.output_scorer
            g = old.stack(sc.candidate.equations, sc.candidate.outputs)
            from solvers.discovery.screening import fitted_values
            from solvers.discovery.scoring_outputs import OutputScorer
            from solvers.shooting import OutputErrorModel
            cm, data, layout, theta_s, x0s = fitted_values(new_req, new_fit)
            r = OutputScorer(OutputErrorModel(cm, data, layout, new_req.options), theta_s, x0s).r
        else:
            return float("nan")
        if g is None or g.size != r.size or np.std(g) == 0 or np.std(r) == 0:
            return float("nan")
        return float(np.corrcoef(r, g)[0, 1])
    except (FitError, RuntimeError, ValueError):
        return float("nan")


def _equation_names(screening: Screening, cand: Candidate) -> str:
    parts = []
    if cand.equations:
        parts.append(", ".join(screening.states[i] for i in sorted(cand.equations)))
    if cand.outputs:
        parts.append(", ".join(f"output {screening.outputs[j]}" for j in sorted(cand.outputs)))
    return "; ".join(parts)


# --- validation and reporting ---------------------------------------------------------------------

def validate(request: DiscoverRequest, model: Model, fit: FitResult, experiments) -> ValidationSummary | None:
    """Simulation metrics on the validation experiments (initial states estimated on a leading window)."""
    if not experiments:
        return None
    from solvers.simulate import validation_metrics
    values = {name: p.value for name, p in fit.parameters.items() if p.experiment is None}
    try:
        res = validation_metrics(model, values, experiments, request.options)
    except (FitError, RuntimeError, ValueError):
        return None
    return ValidationSummary(rmse=res.rmse, fit_percent=res.fit_percent, nrmse=res.nrmse)


def _validation_worse(before: ValidationSummary | None, after: ValidationSummary | None, tol: float) -> str:
    if before is None or after is None:
        return ""
    worse = [f"{o}: NRMSE {before.nrmse[o]:.4g} -> {after.nrmse[o]:.4g}" for o in before.nrmse
             if o in after.nrmse and after.nrmse[o] > before.nrmse[o] * (1 + tol)]
    return "; ".join(worse)


def summarize(fit: FitResult, validation: ValidationSummary | None = None) -> FitSummary:
    return FitSummary(success=fit.success, status=fit.status, rmse=fit.metrics.rmse,
                      fit_percent=fit.metrics.fit_percent, cost=fit.metrics.cost, aic=fit.metrics.aic,
                      bic=fit.metrics.bic, white={a.output: a.whiteness.passed for a in fit.residual_analysis},
                      validation=validation)


def public_scores(screening: Screening) -> list[CandidateScore]:
    best_per_family: dict[str, Scored] = {}
    for sc in screening.scored:
        best_per_family.setdefault(f"{sc.candidate.family}|{sc.scored_on}", sc)
    return [CandidateScore(effect=sc.candidate.effect, equation=_equation_names(screening, sc.candidate),
                           term=sc.candidate.term, explained_variance=sc.score.explained,
                           bic_drop=sc.score.bic_drop, p_value=sc.score.p_value, significant=sc.significant,
                           scored_on=sc.scored_on, record_specific=sc.candidate.record_specific)
            for sc in list(best_per_family.values())[:15]]


def added_inputs(request: DiscoverRequest, final: FitRequest) -> dict:
    out = {}
    original = {e.name: set(e.inputs) for e in request.experiments}
    for exp in final.experiments:
        extra = {k: v for k, v in exp.inputs.items() if k not in original[exp.name]}
        if extra:
            out[exp.name] = extra
    return out
