"""Close the loop: fit, trace the residual to a named missing effect, add it, refit, report.

1. Fit the declared model with the requested method.
2. Build equation residuals (`trace.build_trace`) and score every candidate of the effect library
   (`effects.library`) with a one-step equation-error refit (`trace.EquationScorer`).
3. Screening: a candidate is significant when its F-test p-value is below `significance` divided
   by the number of candidates tried (Bonferroni; scanned switch times and thresholds count each),
   it explains at least `min_explained` of the residual variance of its equations, and its sign is
   physical (friction dissipates).
4. The best significant candidate (largest BIC drop) is added and the whole model refitted with the
   requested method. It is kept only if the refit's BIC falls by `min_bic_drop` and the new
   parameter's |value|/stderr reaches `min_t_value`; otherwise the loop stops.
5. Repeat up to `max_terms`; report before/after, each step's evidence and the augmented model.
"""
from __future__ import annotations

import time

import numpy as np

from schemas.discovery import (
    CandidateScore, DiscoverRequest, DiscoveryResult, DiscoveryStep, Evidence, FitSummary, NewParameter,
)
from schemas.fit import FitRequest, FitResult
from schemas.model import Model
from solvers.data import prepare_experiments
from solvers.errors import ModelDefinitionError
from solvers.expressions import compile_expression
from solvers.discovery.effects import Candidate, library
from solvers.discovery.trace import EquationScorer, build_trace
from solvers.fit import fit_model
from solvers.model_compiler import compile_model
from solvers.parameters import build_layout
from solvers.shooting import OutputErrorModel

__all__ = ["discover"]


def _symbol_env(model: Model) -> dict:
    import casadi as ca
    env = {n: ca.SX.sym(n) for n in [*model.states, *model.inputs, *(p.name for p in model.parameters),
                                     *model.constants, "t"]}
    return env


def summarize(fit: FitResult) -> FitSummary:
    return FitSummary(rmse=fit.metrics.rmse, fit_percent=fit.metrics.fit_percent, cost=fit.metrics.cost,
                      aic=fit.metrics.aic, bic=fit.metrics.bic,
                      white={a.output: a.whiteness.passed for a in fit.residual_analysis})


def _with_estimates(model: Model, fit: FitResult) -> Model:
    """The model with its parameters' initial values set to the fitted ones (inside the bounds)."""
    params = []
    for p in model.parameters:
        est = fit.parameters.get(p.name)
        value = p.value if est is None or p.per_experiment else est.value
        lo = -np.inf if p.lower is None else p.lower
        hi = np.inf if p.upper is None else p.upper
        params.append(p.model_copy(update={"value": float(np.clip(value, lo, hi))}))
    return model.model_copy(update={"parameters": params})


def _trace_for(request: FitRequest, fit: FitResult):
    """Equation residuals of the fitted model (smoothed measurements, else the simulated states)."""
    cm = compile_model(request.model)
    data = prepare_experiments(request.experiments, cm)
    layout = build_layout(request.model, [d.name for d in data])
    theta = np.array([fit.parameters[label].value for label in layout.labels])
    params = [np.asarray(layout.full(e, theta / layout.scale), dtype=float).ravel() for e in range(len(data))]
    oem = OutputErrorModel(cm, data, layout, request.options)
    x0s = []
    for d in data:
        known = fit.initial_states.get(d.name, {})
        x0s.append(np.array([known.get(s, 0.0) for s in cm.states]))
    try:
        simulated = [states for states, _ in oem.simulate(theta, x0s)]
    except RuntimeError:
        simulated = [np.zeros((cm.nx, d.n)) for d in data]
    free = [p.name for p in request.model.parameters if not p.fixed]
    return build_trace(cm, data, params, simulated, free, request.options)


def _screen(request: FitRequest, fit: FitResult, opts, exclude: set[str]):
    trace = _trace_for(request, fit)
    if not trace.traced:
        return [], 0, trace
    scorers: dict[tuple, EquationScorer] = {}

    def scorer_for(equations) -> EquationScorer:
        key = tuple(sorted(equations))
        if key not in scorers:
            scorers[key] = EquationScorer(trace, list(key))
        return scorers[key]

    cands = [c for c in library(request.model, trace, opts.effects, opts.candidates, opts.coulomb_epsilon,
                                scorer_for, opts.significance, opts.min_explained)
             if c.family not in exclude]
    scored: list[tuple[Candidate, object]] = []
    for c in cands:
        if not c.equations:
            continue
        sc = scorer_for(c.equations)
        s = sc.score(sc.stack(c.equations))
        if s is not None:
            scored.append((c, s))
    return scored, sum(c.tries for c in cands), trace


def discover(request: DiscoverRequest) -> DiscoveryResult:
    """Fit, find and add missing effects, refit; see the module docstring for the tests used."""
    started = time.perf_counter()
    opts = request.discovery
    names = set(request.model.states) | set(request.model.inputs) | {p.name for p in request.model.parameters}
    for i, cand in enumerate(opts.candidates):
        if cand.equation not in request.model.states:
            raise ModelDefinitionError(f"'{cand.equation}' is not a state (states: {request.model.states})",
                                       f"discovery.candidates[{i}].equation")
        if cand.parameter in names:
            raise ModelDefinitionError(f"'{cand.parameter}' is already a name in the model; choose a new one",
                                       f"discovery.candidates[{i}].parameter")
        compile_expression(cand.term, _symbol_env(request.model), f"discovery.candidates[{i}].term")
    fit_req = FitRequest(model=request.model, experiments=request.experiments, method=request.method,
                         options=request.options)
    fit = fit_model(fit_req)
    before = summarize(fit)
    steps: list[DiscoveryStep] = []
    rejected: list[str] = []
    screened_first: list[CandidateScore] = []
    tried_families: set[str] = set()
    model = fit_req.model

    for round_no in range(opts.max_terms):
        scored, n_tried, trace = _screen(fit_req, fit, opts, tried_families)
        if not scored:
            break
        alpha = opts.significance / max(n_tried, 1)

        def significant(c: Candidate, s, alpha=alpha) -> bool:
            physical = c.sign == 0 or np.sign(s.beta) == np.sign(c.sign)
            return s.p_value < alpha and s.explained >= opts.min_explained and physical

        scored.sort(key=lambda cs: cs[1].bic_drop, reverse=True)
        if round_no == 0:
            best_per_family: dict[str, tuple] = {}
            for c, s in scored:
                best_per_family.setdefault(c.family, (c, s))
            screened_first = [CandidateScore(effect=c.effect, equation=_eq_names(trace, c), term=c.term,
                                             explained_variance=s.explained, bic_drop=s.bic_drop,
                                             p_value=s.p_value, significant=significant(c, s))
                              for c, s in list(best_per_family.values())[:15]]
        winners = [(c, s) for c, s in scored if significant(c, s)]
        if not winners:
            break
        cand, score = winners[0]
        variants = ([(c, s) for c, s in winners if c.family == cand.family][:4] if cand.refit_variants
                    else [winners[0]])
        best = None
        for c, s in variants:
            new_model, new_params = c.apply(_with_estimates(model, fit))
            experiments = (c.transform_experiments(fit_req.experiments) if c.transform_experiments
                           else fit_req.experiments)
            new_req = fit_req.model_copy(update={"model": new_model, "experiments": experiments,
                                                 "options": _stable_options(fit_req, c, s.beta)})
            try:
                new_fit = fit_model(new_req)
            except Exception as exc:  # a candidate the solver cannot handle is rejected, not fatal
                rejected.append(f"{c.description}: refit failed ({exc})")
                continue
            if best is None or new_fit.metrics.bic < best[3].metrics.bic:
                best = (c, s, new_model, new_fit, new_params, new_req)
        if best is None:
            tried_families.add(cand.family)
            continue
        cand, score, new_model, new_fit, new_params, new_req = best
        t_value = _t_value(new_fit, new_params)
        bic_drop = fit.metrics.bic - new_fit.metrics.bic
        if not new_fit.success or bic_drop < opts.min_bic_drop or (t_value is not None and t_value < opts.min_t_value):
            t_text = "n/a" if t_value is None else round(t_value, 1)
            rejected.append(f"{cand.description}: the refit did not confirm it (BIC drop {bic_drop:.1f}, "
                            f"t = {t_text}, solver {new_fit.solver.return_status})")
            tried_families.add(cand.family)
            break
        after_corr = _correlation_after(new_req, new_fit, cand, trace)
        steps.append(DiscoveryStep(
            effect=cand.effect, equation=_eq_names(trace, cand), term=cand.term, description=cand.description,
            parameters=[NewParameter(name=n, value=new_fit.parameters[n].value, stderr=new_fit.parameters[n].stderr,
                                     ci95=new_fit.parameters[n].ci95) for n in new_params],
            evidence=Evidence(explained_variance=score.explained, screening_bic_drop=score.bic_drop,
                              p_value=score.p_value, bic_before=fit.metrics.bic, bic_after=new_fit.metrics.bic,
                              bic_drop=bic_drop, t_value=t_value,
                              residual_correlation_before=score.corr_before,
                              residual_correlation_after=after_corr),
            after=summarize(new_fit)))
        tried_families.add(cand.family)
        tried_families.update(f"{kind}:{n}" for n in new_params for kind in
                              ("parameter_step", "parameter_drift"))   # no steps of a step
        model, fit, fit_req = new_model, new_fit, new_req

    conclusion = ("no significant missing effect" if not steps else
                  "added " + "; ".join(f"{s.effect} ({s.description})" for s in steps))
    added_inputs = {}
    original = {e.name: set(e.inputs) for e in request.experiments}
    for exp in fit_req.experiments:
        extra = {k: v for k, v in exp.inputs.items() if k not in original[exp.name]}
        if extra:
            added_inputs[exp.name] = extra
    return DiscoveryResult(conclusion=conclusion, before=before, after=summarize(fit), steps=steps,
                           added_inputs=added_inputs,
                           rejected=rejected, screened=screened_first, model=model, fit=fit,
                           wall_time_s=time.perf_counter() - started)


def _stable_options(req: FitRequest, cand: Candidate, beta: float):
    """More RK4 substeps when the new term is stiff (a sharp tanh): |λ|·h ≤ 0.5 keeps RK4 accurate."""
    opts = req.options
    if req.method.value == "equation_error" or opts.integrator != "rk4" or cand.stiffness == 0:
        return opts
    rate = abs(beta) * cand.stiffness
    dt = max(float(np.max(np.diff(e.time))) for e in req.experiments)
    need = int(np.ceil(2 * rate * dt))
    if need <= opts.substeps:
        return opts
    return opts.model_copy(update={"substeps": min(need, 100)})


def _eq_names(trace, cand: Candidate) -> str:
    return ", ".join(trace.cm.states[i] for i in sorted(cand.equations))


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


def _correlation_after(req: FitRequest, fit: FitResult, cand: Candidate, old_trace) -> float:
    """Correlation of the refitted model's equation residual with the candidate's regressor."""
    try:
        trace = _trace_for(req, fit)
        eqs = sorted(cand.equations)
        scorer = EquationScorer(trace, eqs)
        g = scorer.stack(cand.equations)
        if g.size != scorer.r.size or np.std(g) == 0 or np.std(scorer.r) == 0:
            return float("nan")
        return float(np.corrcoef(scorer.r, g)[0, 1])
    except Exception:
        return float("nan")
