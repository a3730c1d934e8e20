"""`fit_online`: recursive least squares or MRAS over one record, returned as a `FitResult`.

The final estimate is the usual `parameters` (with the covariance of the last update); the whole
θ(t) with its ±2σ band is `trajectory`. When the model is linear in its states and inputs but not
in its parameters, the estimator follows the linear coefficients and each one is mapped back to
the physical parameters (`solvers.reparametrize`).
"""
from __future__ import annotations

import time

import casadi as ca
import numpy as np

from greyfit.schemas.fit import (
    CovariancePublic,
    FitMethod,
    FitMetrics,
    FitRequest,
    FitResult,
    ParameterEstimate,
    SolverInfo,
)
from greyfit.schemas.online import ParameterTrajectory, RlsOptions
from greyfit.solvers.checks.diagnostics import residual_analysis
from greyfit.solvers.data.experiments import prepare_experiments
from greyfit.solvers.data.prefilter import apply_prefilter
from greyfit.solvers.errors import DataError
from greyfit.solvers.inference.covariance import correlation_from
from greyfit.solvers.inference.statistics import information_criteria, student_t_quantile
from greyfit.solvers.methods.equation_error import build_equation_error
from greyfit.solvers.methods.online.checks import apply_verdict, bound_warnings, excitation_warnings, outside_bounds
from greyfit.solvers.methods.online.convergence import (
    TAIL,
    disagreement_warnings,
    settling_warnings,
    uncertainty_warnings,
)
from greyfit.solvers.methods.online.recursive import OnlineRun, excitation_report, recursive_least_squares
from greyfit.solvers.methods.online.rls_noise import measurement_noise
from greyfit.solvers.model.compiler import compile_model
from greyfit.solvers.model.discrete import check_sample_time, is_discrete
from greyfit.solvers.model.parameters import build_layout
from greyfit.solvers.model.reparametrize import LinearForm, linear_form, to_physical


def _check_request(request: FitRequest) -> None:
    if len(request.experiments) != 1:
        raise DataError(f"{request.method.value} follows one record; send one experiment "
                        f"({len(request.experiments)} given)", "experiments")
    for i, p in enumerate(request.model.parameters):
        if p.time_varying is not None:
            raise DataError("online estimators track parameter changes by themselves; remove "
                            "time_varying or use a batch method", f"model.parameters[{i}].time_varying")
        if p.per_experiment:
            raise DataError("per_experiment has no meaning with one record", f"model.parameters[{i}]")


def fit_online(request: FitRequest) -> FitResult:
    """Run the online estimator named by `request.method` over the single experiment.

    Parameters
    ----------
    request : FitRequest
        A fit request with `method` recursive least squares or MRAS and exactly one experiment;
        the estimator's settings are `request.options.rls` or `request.options.mras`.

    Returns
    -------
    FitResult
        The final estimate as `parameters` (with the covariance of the last update where the gain law
        gives one), the whole θ(t) with its ±2σ band as `trajectory`, the excitation report, and the
        excitation and bound warnings with their quality verdict.

    Raises
    ------
    DataError
        When the request has more than one experiment, a time-varying or per-experiment parameter,
        every parameter fixed, no state equation depending on a free parameter, or bad data or
        options (from the data preparation and the estimators).
    ModelDefinitionError
        When the model cannot be compiled or brought to a form linear in its coefficients.
    """
    started = time.perf_counter()
    _check_request(request)
    opts = request.options
    cm = compile_model(request.model)
    data = prepare_experiments(request.experiments, cm)
    if is_discrete(cm):
        check_sample_time(cm, data)
    layout = build_layout(request.model, [d.name for d in data])
    if layout.size == 0:
        raise DataError("every parameter is fixed; free at least one", "model.parameters")
    note = None
    if opts.prefilter is not None:
        data, note = apply_prefilter(cm, data, opts.prefilter)
    deps = cm.equation_parameters()
    equations = [i for i, s in enumerate(cm.states) if deps[s] & set(layout.base_names)]
    if not equations:
        raise DataError("no state equation depends on a free parameter; nothing to estimate", "model.parameters")
    form = linear_form(cm, layout, equations)
    # the regressor is equation error's sample Jacobian (linear: evaluated once at η = 0)
    eep = build_equation_error(form.cm, data, form.layout, opts)
    ed, neq = eep.per_experiment[0], len(eep.equations)
    jac, r0 = eep.problem.evaluate_jacobian(np.zeros(form.layout.size))
    phi = jac.reshape(ed.rows.size, neq, form.layout.size)
    y = -r0.reshape(ed.rows.size, neq)
    eta0 = form.layout.initial / form.layout.scale
    reference = None
    if request.method == FitMethod.recursive_least_squares:
        noise = measurement_noise(form, eep.equations, ed.rows) if opts.rls.noise == "measurement" else None
        run = recursive_least_squares(y, phi, eta0, opts.rls, noise)
        every = opts.rls.trajectory_every
    else:
        from greyfit.solvers.methods.online.mras import model_reference_adaptive
        run = model_reference_adaptive(form, data[0], ed, eep.equations, eta0, opts.mras, opts)
        every = opts.mras.trajectory_every
        # RLS on the same regression: what a converged adaptive law must agree with
        reference = _physical(form, layout, recursive_least_squares(y, phi, eta0, RlsOptions()), phi.shape[0])
    d = data[0]
    excitation = excitation_report(phi, run, {u: d.u[k, ed.rows] for k, u in enumerate(cm.inputs)},
                                   linear_regressor=form.mapped or _linear_in_signals(form, equations))
    filt = "; ".join(x for x in (eep.derivative_filter, note) if x) or None
    return _result(request, cm, layout, form, run, eep, d, excitation, every, filt, started, reference)


def _linear_in_signals(form: LinearForm, equations: list[int]) -> bool:
    """Whether the estimated equations are linear in states and inputs (then the regressor is a
    linear filter of the inputs and the PE-order rule applies)."""
    cm = form.cm
    x, u, t = ca.SX.sym("x", cm.nx), ca.SX.sym("u", cm.nu), ca.SX.sym("t")
    eta = ca.SX.sym("eta", form.layout.size)
    p = ca.DM(form.layout.offset) + ca.DM(form.layout.matrix[0]) @ eta
    z = ca.vertcat(x, u)
    jz = ca.jacobian(cm.rhs(x, u, p, t)[equations], z)
    return not ca.depends_on(jz, ca.vertcat(z, t))


def _physical(form: LinearForm, layout, run: OnlineRun, every: int):
    """(final θ, its covariance, trajectory θ (M', nθ), trajectory covariances or None, kept rows)."""
    sc = form.layout.scale
    eta = run.estimates * sc                                    # physical coefficients
    cov = None if run.covariances is None else run.covariances * np.outer(sc, sc)
    keep = np.unique(np.r_[np.arange(0, eta.shape[0], every), eta.shape[0] - 1])
    cov_final = None if cov is None else cov[-1]
    if not form.mapped:
        return eta[-1], cov_final, eta[keep], None if cov is None else cov[keep], keep
    theta_f, cov_f = to_physical(form, eta[-1][:, None], None if cov is None else cov[-1:], layout.initial,
                                 weight_cov=cov_final)
    theta_t, cov_t = to_physical(form, eta[keep].T, None if cov is None else cov[keep], theta_f[:, 0],
                                 weight_cov=cov_final)
    return theta_f[:, 0], None if cov_f is None else cov_f[0], theta_t.T, cov_t, keep


def _band(values: np.ndarray, covs: np.ndarray | None, k: int, sign: float) -> list:
    if covs is None:
        return [None] * values.shape[0]
    sd = np.sqrt(np.maximum(covs[:, k, k], 0.0))
    out = values[:, k] + sign * 2 * sd
    return [float(v) if np.isfinite(v) else None for v in out]


def _floats(a) -> list:
    return [float(v) if np.isfinite(v) else None for v in a]


def _result(request, cm, layout, form, run: OnlineRun, eep, d, excitation, every, filt, started,
            reference=None) -> FitResult:
    opts = request.options
    theta, cov, traj, traj_cov, keep = _physical(form, layout, run, every)
    ed, eqs = eep.per_experiment[0], eep.equations
    m, n = run.estimates.shape
    level_t = student_t_quantile(0.5 + opts.confidence_level / 2, max(m * len(eqs) - n, 1))
    params: dict[str, ParameterEstimate] = {}
    for i, label in enumerate(layout.labels):
        se = float(np.sqrt(cov[i, i])) if cov is not None and cov[i, i] >= 0 else None
        params[label] = ParameterEstimate(
            value=float(theta[i]), stderr=se,
            ci95=None if se is None else (float(theta[i] - level_t * se), float(theta[i] + level_t * se)),
            initial=float(layout.initial[i]))
    for name, value in layout.fixed.items():
        params[name] = ParameterEstimate(value=value, fixed=True, initial=value)
    covariance = correlation = None
    cov_note = None
    if cov is not None and np.all(np.isfinite(cov)) and np.all(np.diag(cov) > 0):
        covariance = CovariancePublic(names=list(layout.labels), matrix=cov.tolist())
        correlation = CovariancePublic(names=list(layout.labels), matrix=correlation_from(cov).tolist())
    else:
        cov_note = ("the covariance of the last update is not positive definite" if run.covariances is not None
                    else "MRAS gives no covariance" if request.method == FitMethod.mras
                    else f"the {opts.rls.gain_law} gain law's P is not a covariance")

    # innovations (one-step a-priori errors) per equation channel, unweighted
    w = eep.weights[eqs] if run.residual_weighted else np.ones(len(eqs))
    innov = run.innovations / w
    measured = ed.dx[eqs][:, ed.rows] if run.measured is None else run.measured
    prefix = "next" if is_discrete(cm) else "der"
    if run.measured is not None:      # MRAS: the output error of the adjustable model
        prefix = "state"
    analyses, rmse, fitp = [], {}, {}
    for c, i in enumerate(eqs):
        name = f"{prefix}({cm.states[i]})"
        a = residual_analysis(name, [(measured[c], innov[:, c], {u: d.u[k, ed.rows] for k, u in enumerate(cm.inputs)})])
        analyses.append(a)
        rmse[name], fitp[name] = a.rmse, a.fit_percent
    weighted = (run.innovations * (1.0 if run.residual_weighted else eep.weights[eqs])).ravel()
    cost = 0.5 * float(weighted @ weighted)
    aic, bic = information_criteria(2 * cost, weighted.size, n)

    t_rows = d.t[ed.rows][keep]
    names = list(layout.labels)
    marks = outside_bounds(traj, layout)
    bounded = [k for k in range(len(names)) if np.isfinite(layout.lower[k]) or np.isfinite(layout.upper[k])]
    trajectory = ParameterTrajectory(
        estimator=run.label, time=t_rows.tolist(),
        values={nm: _floats(traj[:, k]) for k, nm in enumerate(names)},
        lower={nm: _band(traj, traj_cov, k, -1) for k, nm in enumerate(names)},
        upper={nm: _band(traj, traj_cov, k, +1) for k, nm in enumerate(names)},
        coefficients=({nm: _floats(run.estimates[keep, k] * form.layout.scale[k])
                       for k, nm in enumerate(form.layout.labels)} if form.mapped else None),
        mapping=form.descriptions if form.mapped else None,
        excitation=excitation,
        outside_bounds={names[k]: marks[:, k].tolist() for k in bounded} or None,
        note=("physical parameters mapped from the estimated coefficients by weighted Gauss-Newton; "
              "band by the delta method" if form.mapped else None))
    message = (f"{run.label}: {m} updates"
               + ("" if excitation.persistently_exciting else "; not persistently exciting (see warnings)")
               + "; bounds and constraints are not enforced by online estimators")
    result = FitResult(
        success=bool(np.all(np.isfinite(theta))), status="success" if np.all(np.isfinite(theta)) else "failed",
        message=message, parameters=params, confidence_level=opts.confidence_level, covariance=covariance,
        covariance_note=cov_note,
        correlation=correlation,
        initial_states={d.name: {s: float(ed.x[i, ed.rows[0]]) for i, s in enumerate(cm.states)}},
        metrics=FitMetrics(cost=cost, ndata=weighted.size, nfree=weighted.size - n, nvarys=n,
                           rmse=rmse, fit_percent=fitp, aic=aic, bic=bic),
        solver=SolverInfo(method=request.method, iterations=m, wall_time_s=time.perf_counter() - started,
                          return_status="Online_Estimate", derivative_filter=filt,
                          linear_in_parameters=not form.mapped),
        residual_analysis=analyses, trajectory=trajectory)
    return apply_verdict(result, excitation_warnings(excitation) + bound_warnings(theta, layout, marks)
                         + _convergence_warnings(form, run, theta, names, innov, reference, params))


TAIL_SAMPLES = 40   # physical estimates the settling check maps over the record's tail


def _tail_values(form: LinearForm, run: OnlineRun, theta: np.ndarray) -> np.ndarray:
    """(K, nθ) physical estimates at `TAIL_SAMPLES` updates over the record's tail (whatever
    `trajectory_every` keeps for the result)."""
    m = run.estimates.shape[0]
    idx = np.unique(np.linspace(int(m * (1 - TAIL)), m - 1, TAIL_SAMPLES).astype(int))
    eta = run.estimates[idx] * form.layout.scale
    if not form.mapped:
        return eta
    return to_physical(form, eta.T, None, theta)[0].T


def _convergence_warnings(form, run, theta, names, innov, reference, params) -> list:
    """The trajectory and the error settled, the estimate precise; MRAS beside RLS's (final θ,
    covariance) when given, RLS's standard errors standing for the precision MRAS does not give."""
    out = settling_warnings(_tail_values(form, run, theta), names, innov)
    if reference is not None:
        cov_rls = reference[1]
        sd = None if cov_rls is None else np.sqrt(np.maximum(np.diag(cov_rls), 0.0))
        out += disagreement_warnings(names, theta, reference[0], sd)
    else:
        errors = [params[n].stderr for n in names]
        sd = None if any(e is None for e in errors) else np.array(errors, dtype=float)
    return out + uncertainty_warnings(names, theta, sd)
