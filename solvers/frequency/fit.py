"""`fit_frequency_response`: Levy/SK start, Ipopt fit with stability constraints, covariance, report."""
from __future__ import annotations

import dataclasses
import time

import casadi as ca
import numpy as np

from greyfit.schemas.fit import (
    CovariancePublic,
    FitMethod,
    FitMetrics,
    FitOptions,
    FitResult,
    ParameterEstimate,
    SolverInfo,
)
from greyfit.schemas.frequency import (
    DataSetResponse,
    FrequencyFitRequest,
    FrequencyResponseResult,
    LinearisedOdeModel,
    LoopStability,
)
from greyfit.solvers.errors import DataError
from greyfit.solvers.fit import _at_bound, _message
from greyfit.solvers.frequency.checks import assess_frequency_fit
from greyfit.solvers.frequency.data import prepare_frequency_data
from greyfit.solvers.frequency.lack_of_fit import trend_warnings
from greyfit.solvers.frequency.levy import levy_fit
from greyfit.solvers.frequency.linearise import CompiledLinearisedModel, compile_linearised_model
from greyfit.solvers.frequency.polynomials import ClosedLoop, CompiledTransferFunction, compile_transfer_function
from greyfit.solvers.frequency.problem import FrequencyProblem, build_frequency_problem, data_weights
from greyfit.solvers.frequency.response import numeric_response
from greyfit.solvers.frequency.stability import poles, routh_first_column
from greyfit.solvers.inference.covariance import correlation_from, estimate_covariance
from greyfit.solvers.inference.statistics import information_criteria
from greyfit.solvers.methods.multistart import (
    CPU_STATUSES,
    MULTISTART_CPU_STATUS,
    MultistartRun,
    draw_starts,
    multistart_agreement,
    multistart_warnings,
)
from greyfit.solvers.model.carried import attach_model
from greyfit.solvers.model.parameters import build_layout
from greyfit.solvers.nlp.solver import SUCCESS_STATUSES, LeastSquaresSolver, NlpOutcome

FEASIBILITY_TOLERANCE = 1e-7


def _engine_options(request: FrequencyFitRequest) -> FitOptions:
    o = request.options
    return FitOptions(max_iter=o.max_iter, max_cpu_time=o.max_cpu_time, tol=o.tol, hessian=o.hessian,
                      multistart=o.multistart, seed=o.seed, confidence_level=o.confidence_level)


def _feasible(fp: FrequencyProblem, w: np.ndarray) -> bool:
    p = fp.problem
    if p.g.numel() == 0:
        return True
    gval = np.array(ca.Function("g", [p.w], [p.g])(w)).ravel()
    return bool(np.all(gval >= p.lbg - FEASIBILITY_TOLERANCE) and np.all(gval <= p.ubg + FEASIBILITY_TOLERANCE))


def _interior(theta: np.ndarray, layout) -> np.ndarray:
    """Move a start a little inside its bounds (Levy often lands on a bound)."""
    lo, hi = layout.lower, layout.upper
    width = np.where(np.isfinite(hi - lo), hi - lo, layout.scale)
    return np.clip(theta, lo + 1e-3 * width, hi - 1e-3 * width)


def _solve_multistart(fp: FrequencyProblem, starts: list[np.ndarray], options: FitOptions) -> MultistartRun:
    """Every start to its own end (iteration limits only); the best: converged and feasible first,
    then feasible, then the lower cost. In the run's `outcomes` (read by `multistart_agreement`
    only) `success` also asks feasibility, so only feasible converged starts count as optima.
    `max_cpu_time` is a safety net: when it cuts the multistart off, or ends one start's solve,
    the best is not converged, with status MULTISTART_CPU_STATUS."""
    solver = LeastSquaresSolver(fp.problem, options)
    best: NlpOutcome | None = None
    best_key: tuple[bool, bool, float] | None = None   # set together with best
    outcomes: list[NlpOutcome] = []
    cpu0 = time.process_time()
    for theta0 in starts:
        if best is not None and time.process_time() - cpu0 > options.max_cpu_time:
            break
        out = solver.solve(fp.problem.initial_guess(theta0))
        feasible = _feasible(fp, out.w)
        outcomes.append(dataclasses.replace(out, success=out.success and feasible))
        key = (out.success and feasible, feasible, -out.cost)
        if best_key is None or key > best_key:
            best, best_key = out, key
    if best is None:
        raise ValueError("no start to solve from")   # starts always hold the user's guess
    if len(outcomes) > 1 and (len(outcomes) < len(starts) or any(o.status in CPU_STATUSES for o in outcomes)):
        # the safety net cut the multistart off, and says so: not the answer of all starts
        best = dataclasses.replace(best, status=MULTISTART_CPU_STATUS, success=False)
    return MultistartRun(best, outcomes, len(starts))


def _loop_report(loop: ClosedLoop, p: np.ndarray) -> LoopStability:
    den = np.array(loop.den_fn(p)).ravel()
    if not np.all(np.isfinite(den)):   # e.g. a linearised model with no equilibrium there
        return LoopStability(setting=loop.name, poles_real=[], poles_imag=[], max_real_part=None, stable=False,
                             routh_first_column=[])
    pl = poles(den)
    mx = float(np.max(pl.real)) if pl.size else -np.inf
    return LoopStability(setting=loop.name, poles_real=pl.real.tolist(), poles_imag=pl.imag.tolist(),
                         max_real_part=mx, stable=bool(mx < 0), routh_first_column=routh_first_column(den))


def _check_finite_loops(loops: list[ClosedLoop], extra: list[ClosedLoop], layout) -> None:
    """Each closed loop's coefficients are finite at the initial values, else a DataError naming the
    constants that overflowed them (e.g. Ki = 1e308: finite, but its products are not)."""
    p0 = layout.initial / layout.scale
    for k, loop in enumerate(loops + extra):
        p = layout.full(k if k < len(loops) else 0, p0)
        coefficients = np.concatenate([np.array(loop.num_fn(p), dtype=float).ravel(),
                                       np.array(loop.den_fn(p), dtype=float).ravel()])
        if not np.all(np.isfinite(coefficients)):
            field = f"data[{k}].constants" if k < len(loops) else f"options.{loop.name}"
            raise DataError("the closed loop's coefficients overflow at the initial parameter values: "
                            "use units that keep the constants and parameters well inside ±1e150", field)


def fit_frequency_response(request: FrequencyFitRequest) -> FitResult:
    """Fit a transfer-function (or linearised ODE) model to measured frequency responses.

    A Levy start refined by Sanathanan-Koerner reweightings, then Ipopt on the chosen cost, with
    the closed loops' stability constrained (Routh-Hurwitz), penalised or only checked.

    Parameters
    ----------
    request : FrequencyFitRequest
        The model (`kind: "transfer_function"` or `"linearised_ode"`, optionally inside a known
        feedback loop), the data sets (complex, gain/phase or raw sine-test records) and the
        options.

    Returns
    -------
    FitResult
        The estimates with their covariance and metrics, plus `frequency_response`: measured and
        fitted responses per data set, zeros, and per loop the poles and a stability verdict.
        A fit that does not converge, or ends with an unstable loop, is a result with
        `success: false`.

    Raises
    ------
    ModelDefinitionError, DataError
        The model does not compile, or the data do not fit it; `field` names where the fix goes.
    """
    started = time.perf_counter()
    opts = request.options
    engine_opts = _engine_options(request)
    tf: CompiledTransferFunction
    if isinstance(request.model, LinearisedOdeModel):
        tf = compile_linearised_model(request.model)
    else:
        tf = compile_transfer_function(request.model)
    sets = prepare_frequency_data(request.data, request.model)
    unknown = [(k, name) for k, c in enumerate(opts.also_stable_with) for name in c
               if name not in request.model.constants]
    if unknown:
        k, name = unknown[0]
        raise DataError(f"'{name}' is not a model constant; declare it in model.constants",
                        f"options.also_stable_with[{k}].{name}")
    if opts.cost in ("relative_complex", "log"):
        for i, s in enumerate(sets):
            if np.any(np.abs(s.response) == 0):
                raise DataError(f"|G| = 0 at ω = {s.omega[np.argmax(np.abs(s.response) == 0)]:g}: a relative "
                                "or log cost cannot use it; drop the point or set options.cost to 'complex'",
                                f"data[{i}]")
    layout = build_layout(request.model, [s.name for s in sets])   # uses only model.parameters
    if layout.size == 0:
        raise DataError("every parameter is fixed; free at least one", "model.parameters")
    ndata = 2 * sum(s.omega.size for s in sets)
    if ndata <= layout.size:
        raise DataError(f"{ndata} residuals for {layout.size} free parameters; measure more frequencies", "data")

    loops = [tf.loop(s.name, s.constants) for s in sets]
    extra = [tf.loop(f"also_stable_with[{k}]", c) for k, c in enumerate(opts.also_stable_with)]
    if not isinstance(request.model, LinearisedOdeModel):   # (a linearised model's NaN has its own report)
        _check_finite_loops(loops, extra, layout)
    stability_loops = [(loop, e) for e, loop in enumerate(loops)] + [(loop, 0) for loop in extra]
    fp = build_frequency_problem(tf, loops, stability_loops, sets, layout, opts)

    starts = draw_starts(layout, opts.multistart, opts.seed)
    levy_theta, levy_status = None, None
    if opts.levy_start:
        # unconstrained: a constrained Levy step lands on a bound far from the truth and SK cannot
        # leave it (seen on the frequency-data course notes' structure); bounds and constraints act in the fit proper
        levy = levy_fit(loops, sets, layout, iterations=opts.sk_iterations,
                        data_weights=data_weights(sets, opts.cost), constrained=False, options=engine_opts)
        if np.all(np.isfinite(levy.theta)) and levy.status in SUCCESS_STATUSES:   # else it is just the start
            levy_theta = levy.theta
            starts.insert(0, _interior(levy.theta, layout))
        levy_status = levy.status
    run = _solve_multistart(fp, starts, engine_opts)
    if levy_status in CPU_STATUSES:
        # the safety net stopped the Levy fit: the start a quiet machine has is missing, so no answer
        run.best = dataclasses.replace(run.best, status=levy_status, success=False)
    outcome, n_starts = run.best, run.used
    if not np.all(np.isfinite(np.array(fp.data_residual(outcome.w), dtype=float))):
        # e.g. a linearised model whose equilibrium does not exist there: report the start instead
        outcome.w, outcome.success = fp.problem.initial_guess(layout.initial), False
        outcome.status = "Invalid_Number_Detected"

    theta_s = outcome.w[:layout.size]
    theta = layout.physical(theta_s)
    bounds = _at_bound(layout, theta_s)
    data_r = fp.problem.residual[:fp.n_data_rows]   # the stability penalty rows are not data
    jac_fn = ca.Function("data_jacobian", [fp.problem.w], [ca.jacobian(data_r, fp.problem.w), data_r])
    jac, res = (np.array(x) for x in jac_fn(outcome.w))
    res = res.ravel()
    keep = np.array([b is None for b in bounds])
    cov = estimate_covariance(jac, res, list(layout.labels), theta, layout.scale, keep, layout.size,
                              opts.confidence_level)
    notes = list(fp.notes) + list(getattr(tf, "notes", []))
    if cov.note:
        notes.insert(0, cov.note)
    active = _active_stability(fp, outcome.w, opts.stability_margin)
    if active and opts.stability == "routh":
        notes.append(f"stability constraint active at the solution ({', '.join(active)}): the covariance "
                     "ignores it and the data alone would prefer a less stable loop")

    params: dict[str, ParameterEstimate] = {}
    for i, label in enumerate(layout.labels):
        params[label] = ParameterEstimate(
            value=float(theta[i]), stderr=cov.stderr.get(label), ci95=cov.ci.get(label), at_bound=bounds[i],
            initial=float(layout.initial[i]), experiment=layout.experiment[i])
    for name, value in layout.fixed.items():
        params[name] = ParameterEstimate(value=value, fixed=True, initial=value)

    response = _response_report(loops, extra, sets, layout, theta_s, opts, levy_theta)
    if isinstance(tf, CompiledLinearisedModel):
        response.operating_point = tf.operating_point(np.array(layout.full(0, theta_s), dtype=float).ravel())
    nvarys = int(keep.sum())
    cost = 0.5 * float(res @ res)
    aic, bic = information_criteria(2 * cost, ndata, nvarys)
    rmse: dict[str, float | None] = {}
    fitp: dict[str, float | None] = {}
    for d in response.data:
        meas = np.array(d.measured_real) + 1j * np.array(d.measured_imag)
        err = np.array(d.fitted_real) + 1j * np.array(d.fitted_imag) - meas
        rmse[d.name] = float(np.sqrt(np.mean(np.abs(err) ** 2)))
        spread = np.linalg.norm(meas - meas.mean())
        fitp[d.name] = float(100 * (1 - np.linalg.norm(err) / spread)) if spread > 0 else float("nan")
    message = _message(outcome.status)
    if not response.stable:
        bad = [lp.setting for lp in response.loops if not lp.stable]
        message += f"; the fitted closed loop is UNSTABLE for {bad} (see frequency_response.loops)"
    covariance = correlation = None
    if cov.matrix is not None:
        covariance = CovariancePublic(names=cov.names, matrix=cov.matrix.tolist())
        correlation = CovariancePublic(names=cov.names, matrix=correlation_from(cov.matrix).tolist())
    result = attach_model(FitResult(
        success=outcome.success, status="success" if outcome.success else "failed", message=message, parameters=params,
        confidence_level=opts.confidence_level, covariance=covariance, covariance_note="; ".join(notes) or None,
        correlation=correlation,
        initial_states={s.name: {} for s in sets},
        metrics=FitMetrics(cost=cost, ndata=ndata, nfree=ndata - nvarys, nvarys=nvarys, rmse=rmse,
                           fit_percent=fitp, aic=aic, bic=bic),
        solver=SolverInfo(method=FitMethod.frequency_response, iterations=outcome.iterations,
                          wall_time_s=time.perf_counter() - started, return_status=outcome.status,
                          starts=n_starts),
        frequency_response=response), request.model)
    # as in the time domain: how many starts reached the best cost, and the distinct optima as good
    agree = multistart_agreement(run, layout, ndata, nvarys, opts.confidence_level)
    if agree is not None:
        result.solver.starts_at_best = agree.starts_at_best
        result.alternative_optima = agree.optima or None
    return assess_frequency_fit(result, sets=sets, layout=layout, theta_s=theta_s, converged=outcome.success,
                                status=outcome.status, nlp_cost=outcome.cost, covariance=cov, jac=jac, keep=keep,
                                stability_enforced=opts.stability in ("routh", "penalty"),
                                before=multistart_warnings(run, agree) + trend_warnings(
                                    sets, response, data_weights(sets, opts.cost), opts.cost, res,
                                    jac[:, :layout.size][:, keep]))


def _active_stability(fp: FrequencyProblem, w: np.ndarray, margin: float) -> list[str]:
    if fp.stability is None:
        return []
    h = np.array(fp.stability(w)).ravel()
    return [lab for lab, v in zip(fp.stability_labels, h) if v <= margin * (1 + 1e-3) + 1e-9]


def _response_report(loops, extra, sets, layout, theta_s, opts, levy_theta) -> FrequencyResponseResult:
    data = []
    reports = []
    for e, (loop, s) in enumerate(zip(loops, sets)):
        p = np.array(layout.full(e, theta_s), dtype=float).ravel()
        num, den = np.array(loop.num_fn(p)).ravel(), np.array(loop.den_fn(p)).ravel()
        fitted = numeric_response(num, den, s.omega)
        zeros = poles(num)
        data.append(DataSetResponse(
            name=s.name, omega=s.omega.tolist(), measured_real=s.response.real.tolist(),
            measured_imag=s.response.imag.tolist(), fitted_real=fitted.real.tolist(),
            fitted_imag=fitted.imag.tolist(), zeros_real=zeros.real.tolist(), zeros_imag=zeros.imag.tolist(),
            numerator=num.tolist(), denominator=den.tolist()))
        reports.append(_loop_report(loop, p))
    p0 = np.array(layout.full(0, theta_s), dtype=float).ravel()
    reports += [_loop_report(loop, p0) for loop in extra]
    return FrequencyResponseResult(
        data=data, loops=reports, stable=all(r.stable for r in reports), cost_kind=opts.cost,
        stability_handling=opts.stability,
        levy_start=None if levy_theta is None else dict(zip(layout.labels, map(float, levy_theta))))
