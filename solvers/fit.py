"""`fit_model`: compile, build the chosen problem, solve (multistart), covariance, diagnostics."""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from greyfit.schemas.fit import (
    CovariancePublic, ExperimentTrace, FitMethod, FitMetrics, FitRequest, FitResult,
    ParameterEstimate, SolverInfo,
)
from greyfit.solvers.inference.covariance import correlation_from, estimate_covariance
from greyfit.solvers.data.experiments import ExperimentData, prepare_experiments
from greyfit.solvers.checks.diagnostics import residual_analyses
from greyfit.solvers.methods.equation_error import EquationErrorProblem, build_equation_error
from greyfit.solvers.errors import DataError
from greyfit.solvers.methods.fixed_fit import fixed_parameter_result
from greyfit.solvers.checks.fit_checks import (
    active_constraints, fastest_rate_warning, pre_fit_warnings, row_keys, state_peaks,
)
from greyfit.solvers.methods.extensions import prepare_batch
from greyfit.solvers.model.compiler import CompiledModel, compile_model
from greyfit.solvers.methods.node_initialisation import node_warnings
from greyfit.solvers.nlp.solver import NlpOutcome, solve_linear_least_squares
from greyfit.solvers.model.parameters import ParameterLayout, build_layout
from greyfit.solvers.data.preprocess import prepare_request
from greyfit.solvers.inference.profile import check_profile_names, run_profiles
from greyfit.solvers.methods.shooting import (
    OutputErrorModel, build_multiple_shooting, build_single_shooting, sensitivity_jacobian,
)
from greyfit.solvers.checks.quality import QualityInputs, assess_fit
from greyfit.solvers.checks.step_choice import choose_substeps, substeps_retry
from greyfit.solvers.checks.verdict import review_fit
from greyfit.solvers.methods.shooting_curvature import make_solver
from greyfit.solvers.inference.statistics import information_criteria
from greyfit.solvers.simulation.validate import validate_fit

BOUND_TOLERANCE = 1e-5


@dataclass
class Residuals:
    """Unweighted residual (model − measured) and measured signal per reported channel."""

    channels: list[str]
    per_experiment: list[tuple[np.ndarray, np.ndarray]]  # (measured, residual), each (nch, N)
    states: list[np.ndarray] | None = None   # simulated states per experiment (output error)


def draw_starts(layout: ParameterLayout, n: int, seed: int) -> list[np.ndarray]:
    """The user's guess first, then n-1 draws inside the bounds (log-uniform over decades)."""
    starts = [layout.initial.copy()]
    rng = np.random.default_rng(seed)
    for _ in range(n - 1):
        theta = np.empty(layout.size)
        for i in range(layout.size):
            lo, hi, v = layout.lower[i], layout.upper[i], layout.initial[i]
            lo = lo if np.isfinite(lo) else v - 0.5 * layout.scale[i]
            hi = hi if np.isfinite(hi) else v + 0.5 * layout.scale[i]
            if lo > 0 and hi / lo > 10:
                theta[i] = np.exp(rng.uniform(np.log(lo), np.log(hi)))
            else:
                theta[i] = rng.uniform(lo, hi)
        starts.append(theta)
    return starts


def _solve(problem, options, starts, linear: bool, cpu0: float | None = None) -> tuple[NlpOutcome, int, bool | None]:
    """(best outcome, starts used, whether compiled C evaluated the model); `cpu0`: the process
    time the fit began at (its preparation counts against max_cpu_time too)."""
    if linear:
        outcome = solve_linear_least_squares(problem, options)
        if outcome is not None:
            return outcome, 1, None
    solver = make_solver(problem, options)   # multiple shooting: with its gaps' curvature
    best, used = None, 0
    cpu0 = time.process_time() if cpu0 is None else cpu0
    solving = time.process_time()
    for theta0 in starts:
        now = time.process_time()
        # max_cpu_time bounds the whole fit, not each start: another start is begun only if one
        # more, at the cost of those so far, still ends inside it
        if best is not None and now - cpu0 + (now - solving) / used > options.max_cpu_time:
            break
        out = solver.solve(problem.initial_guess(theta0))
        used += 1
        if best is None or (out.success, -out.cost) > (best.success, -best.cost):
            best = out
    return best, used, getattr(solver, "compiled", None)


def _at_bound(layout: ParameterLayout, theta_s: np.ndarray) -> list[str | None]:
    lo, hi = layout.lower / layout.scale, layout.upper / layout.scale
    flags = []
    for i, v in enumerate(theta_s):
        if np.isfinite(lo[i]) and v - lo[i] <= BOUND_TOLERANCE * max(1.0, abs(lo[i])):
            flags.append("lower")
        elif np.isfinite(hi[i]) and hi[i] - v <= BOUND_TOLERANCE * max(1.0, abs(hi[i])):
            flags.append("upper")
        else:
            flags.append(None)
    return flags


def fit_model(request: FitRequest) -> FitResult:
    """Fit the request's model to its experiments; see `schemas.fit.FitResult`.

    Online estimators go their own way; otherwise each experiment's `preprocess` is applied first
    and `validation` records are simulated after.
    """
    if request.method in (FitMethod.recursive_least_squares, FitMethod.mras):   # online estimators
        from greyfit.solvers.methods.online.estimate import fit_online
        return fit_online(request)
    prepared, preprocessing = choose_substeps(*prepare_request(request))
    result = _fit_prepared(prepared)
    retry = substeps_retry(prepared, result.model_copy(update={"preprocessing": preprocessing}))
    if retry is not None:   # the chosen substeps proved coarse at the estimates: once more, finer
        (prepared, preprocessing), result = retry, _fit_prepared(retry[0])
    if prepared.validation:
        result.validation = validate_fit(prepared, result)
    result.preprocessing = preprocessing
    return review_fit(prepared, result)   # lack of fit and input handling in the verdict


def _fit_prepared(request: FitRequest) -> FitResult:
    started, cpu0 = time.perf_counter(), time.process_time()
    opts = request.options
    cm = compile_model(request.model)
    data = prepare_experiments(request.experiments, cm)
    ext = prepare_batch(request, cm, data)   # discrete-time checks, prefilter, time-varying parameters
    cm, data = ext.cm, ext.data
    layout = build_layout(ext.model, [d.name for d in data])
    if layout.size == 0:   # nothing to estimate: a simulation, reported like a fit
        return fixed_parameter_result(request, cm, data, layout, started)
    unknown_w = sorted(set(opts.output_weights) - set(cm.outputs))
    if unknown_w:
        raise DataError(f"'{unknown_w[0]}' is not an output (outputs: {cm.outputs})",
                        f"options.output_weights.{unknown_w[0]}")
    starts = draw_starts(layout, opts.multistart, opts.seed)
    check_profile_names(opts.profile, list(layout.labels))

    eep: EquationErrorProblem | None = None
    oem: OutputErrorModel | None = None
    if request.method == FitMethod.equation_error:
        eep = build_equation_error(cm, data, layout, opts)
        problem = eep.problem
        ext.attach(problem, layout)
    else:
        oem = OutputErrorModel(cm, data, layout, opts)
        build = build_single_shooting if request.method == FitMethod.single_shooting else build_multiple_shooting
        problem = build(oem)
        ext.attach(problem, layout)
    before = pre_fit_warnings(cm, data, layout, opts, problem, eep, oem)
    if eep is not None:
        affine = ext.solve_affine(problem, layout, eep.linear)
        outcome, n_starts, is_c = ((*affine, None) if affine
                                   else _solve(problem, opts, starts, eep.linear and problem.penalty is None, cpu0))
        if outcome.status == "Linear_Least_Squares":   # the per-sample Jacobian was all that ran
            is_c = eep.sample.compiled
    else:
        outcome, n_starts, is_c = _solve(problem, opts, starts, False, cpu0)
    if not np.all(np.isfinite(outcome.w)):   # report the start rather than NaN estimates
        outcome.w, outcome.success = problem.initial_guess(layout.initial), False

    theta_s = outcome.w[:layout.size]
    theta = layout.physical(theta_s)
    bounds = _at_bound(layout, theta_s)
    x0s = problem.x0_of(outcome.w)

    # Jacobian and residual for the covariance; for multiple shooting the nodes are eliminated
    # by using the single-shooting residual at the solution (gaps are zero there).
    if eep is not None:
        jac, res = problem.evaluate_jacobian(outcome.w)
        groups = np.concatenate([np.tile(np.arange(len(eep.equations)), ed.rows.size)
                                 for ed in eep.per_experiment])
        labels, values, scale = list(layout.labels), theta, layout.scale
        n_extra = 0
    else:
        x0_free = [x0s[e][cm.states[i]] / oem.xscale[i] for e, f in enumerate(oem.free_x0) for i in f]
        labels = list(layout.labels) + oem.x0_labels()
        x0_scale = [oem.xscale[i] for f in oem.free_x0 for i in f]
        scale = np.concatenate([layout.scale, x0_scale])
        values = np.concatenate([theta, np.array(x0_free) * np.array(x0_scale, dtype=float)])
        n_extra = len(x0_free)
        jac, res, groups = sensitivity_jacobian(oem, theta_s, x0s)
    keep = np.array([b is None for b in bounds] + [True] * n_extra)

    ndata = res.size
    nvarys = int(keep.sum())
    cost = 0.5 * float(res @ res)
    aic, bic = information_criteria(2 * cost, ndata, nvarys)
    channels = _residuals(cm, data, eep, oem, theta, x0s, res)
    segments = []
    for c, name in enumerate(channels.channels):
        segments.append([])
        for d, (meas, r) in zip(data, channels.per_experiment):
            ok = np.isfinite(meas[c]) & np.isfinite(r[c])
            segments[-1].append((meas[c][ok], r[c][ok], {u: d.u[k][ok] for k, u in enumerate(cm.inputs)}))
    analyses = residual_analyses(channels.channels, segments)
    rmse = {a.output: a.rmse for a in analyses}
    fitp = {a.output: a.fit_percent for a in analyses}
    white = all(a.whiteness.passed or not a.whiteness.lags for a in analyses)
    robust = opts.robust_covariance == "always" or (opts.robust_covariance == "auto" and not white)
    sample_keys, experiment_keys = row_keys(data, eep, cm)
    cov = estimate_covariance(jac, res, labels, values, scale, keep, layout.size, opts.confidence_level,
                              groups=groups, sample_keys=sample_keys, experiment_keys=experiment_keys,
                              robust=robust)

    params: dict[str, ParameterEstimate] = {}
    for i, label in enumerate(layout.labels):
        params[label] = ParameterEstimate(
            value=float(theta[i]), stderr=cov.stderr.get(label), ci95=cov.ci.get(label),
            at_bound=bounds[i], initial=float(layout.initial[i]), experiment=layout.experiment[i],
            stderr_classical=cov.classical_stderr.get(label, cov.stderr.get(label)))
    for name, value in layout.fixed.items():
        params[name] = ParameterEstimate(value=value, fixed=True, initial=value)

    covariance = correlation = None
    if cov.matrix is not None:
        covariance = CovariancePublic(names=cov.names, matrix=cov.matrix.tolist())
        correlation = CovariancePublic(names=cov.names, matrix=correlation_from(cov.matrix).tolist())
    initial_states = {d.name: x0s[e] for e, d in enumerate(data)} if oem is not None else {
        d.name: {s: float(eep.per_experiment[e].x[i, eep.per_experiment[e].rows[0]])
                 for i, s in enumerate(cm.states)} for e, d in enumerate(data)}
    traces = None
    if opts.return_traces:
        traces = [ExperimentTrace(
            name=d.name, time=d.t.tolist(),
            simulated={ch: (meas[c] + r[c]).tolist() for c, ch in enumerate(channels.channels)},
            residuals={ch: [None if not np.isfinite(v) else float(v) for v in r[c]]
                       for c, ch in enumerate(channels.channels)})
            for d, (meas, r) in zip(data, channels.per_experiment)]
    result = FitResult(
        success=outcome.success, status="success" if outcome.success else "failed",
        message=_message(outcome.status), parameters=params,
        covariance=covariance, covariance_note=cov.note, correlation=correlation,
        initial_states=initial_states,
        metrics=FitMetrics(cost=cost, ndata=ndata, nfree=ndata - nvarys, nvarys=nvarys,
                           rmse=rmse, fit_percent=fitp, aic=aic, bic=bic),
        solver=SolverInfo(method=request.method, iterations=outcome.iterations,
                          wall_time_s=time.perf_counter() - started, return_status=outcome.status,
                          starts=n_starts,
                          derivative_filter=eep.derivative_filter if eep else None,
                          linear_in_parameters=eep.linear if eep else None, compiled=is_c),
        residual_analysis=analyses, traces=traces,
        covariance_classical=None if cov.classical is None else CovariancePublic(
            names=cov.names, matrix=cov.classical.tolist()),
        active_constraints=active_constraints(cm, layout, theta_s))
    result.profile = run_profiles(problem, opts, outcome, layout, ndata, nvarys, cov)
    result = ext.finish(result, layout, theta, cov)
    # parameter columns, rescaled to a 100 % change of the estimate (at least of its initial scale)
    size = np.maximum(np.abs(values) / scale, 1.0)
    params_kept = keep & (np.arange(keep.size) < layout.size)
    return assess_fit(result, _quality_inputs(result, outcome, request, cov, (jac * size)[:, params_kept],
                                              labels, params_kept,
                                              channels, oem, layout, theta_s, x0s, before, opts))


def _quality_inputs(result, outcome, request, cov, jac, labels, keep, channels, oem, layout, theta_s,
                    x0s, before, opts) -> QualityInputs:
    """Collect what `solvers.quality` checks; state sizes and step size only for output error."""
    fitted = guess = None
    if oem is not None and channels.states is not None:
        fitted, guess = state_peaks(oem, channels.states, layout.initial)
        before = before + fastest_rate_warning(oem.cm, oem.data, layout, theta_s, channels.states, opts)
    failures = list(oem.simulation_failures) if oem is not None else []
    before = before + node_warnings(oem)
    signed = {lab for i, lab in enumerate(layout.labels)
              if layout.lower[i] >= 0 or layout.upper[i] <= 0}
    return QualityInputs(
        converged=outcome.success, status=outcome.status, cost=result.metrics.cost if
        result.metrics.cost is not None else float("nan"), nlp_cost=outcome.cost,
        method=request.method.value, covariance=cov, jac=jac,
        jac_labels=[lab for lab, k in zip(labels, keep) if k],
        measured={ch: [m[c] for m, _ in channels.per_experiment] for c, ch in enumerate(channels.channels)},
        fitted_state_peak=fitted, guess_state_peak=guess, state_names=list(request.model.states),
        simulation_failures=failures, before=before, active_constraints=result.active_constraints,
        sign_constrained=signed)


def _message(status: str) -> str:
    return {
        "Solve_Succeeded": "Ipopt converged to the requested tolerance",
        "Solved_To_Acceptable_Level": "Ipopt converged to an acceptable level",
        "Linear_Least_Squares": "solved in closed form (residual affine in the parameters, no active bound)",
        "Maximum_Iterations_Exceeded": "Ipopt stopped at max_iter; raise options.max_iter or improve the guess",
        "Maximum_CpuTime_Exceeded": "Ipopt stopped at max_cpu_time; raise options.max_cpu_time",
        "Infeasible_Problem_Detected": "the bounds and constraints cannot all hold",
    }.get(status, f"Ipopt returned {status}")


def _residuals(cm: CompiledModel, data: list[ExperimentData], eep, oem, theta, x0s,
               weighted_residual: np.ndarray) -> Residuals:
    """Unweighted residuals: simulated outputs for output error, derivatives for equation error.

    For equation error they are the solver's own weighted residual (measured − model), unweighted.
    """
    if eep is not None:
        per, start = [], 0
        neq = len(eep.equations)
        w = eep.weights[eep.equations][:, None]
        for e, d in enumerate(data):
            ed = eep.per_experiment[e]
            block = weighted_residual[start:start + neq * ed.rows.size].reshape(ed.rows.size, neq).T
            start += neq * ed.rows.size
            meas = np.full((neq, d.n), np.nan)
            resid = np.full((neq, d.n), np.nan)
            meas[:, ed.rows] = ed.dx[eep.equations][:, ed.rows]
            resid[:, ed.rows] = -block / w
            per.append((meas, resid))
        return Residuals([f"der({cm.states[i]})" for i in eep.equations], per)
    sims = oem.simulate(theta, [np.array([x0s[e][s] for s in cm.states]) for e in range(len(data))])
    per = [(d.y, ys - d.y) for d, (_, ys) in zip(data, sims)]
    return Residuals(list(cm.outputs), per, [xs for xs, _ in sims])
