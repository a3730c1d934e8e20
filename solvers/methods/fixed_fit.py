"""A fit request with every parameter fixed is a simulation: metrics and diagnostics, no covariance."""
from __future__ import annotations

import time

import numpy as np

from greyfit.schemas.fit import ExperimentTrace, FitMetrics, FitRequest, FitResult, ParameterEstimate, SolverInfo
from greyfit.solvers.checks.diagnostics import residual_analysis
from greyfit.solvers.data.experiments import ExperimentData
from greyfit.solvers.inference.statistics import information_criteria
from greyfit.solvers.methods.shooting import OutputErrorModel
from greyfit.solvers.model.compiler import CompiledModel
from greyfit.solvers.model.parameters import ParameterLayout
from greyfit.solvers.simulation.simulate import estimate_initial_state


def fixed_parameter_result(request: FitRequest, cm: CompiledModel, data: list[ExperimentData],
                           layout: ParameterLayout, started: float) -> FitResult:
    """Simulate the model at its (fixed) parameter values and report it like a fit.

    Initial states not given in the experiments are estimated on the whole record with the
    parameters fixed, as a fit would (they count in `nvarys`). Whatever the requested method, the
    metrics are output error (simulated outputs), since nothing is estimated from derivatives.

    Parameters
    ----------
    request : FitRequest
        The fit request (method and options).
    cm : CompiledModel
        The compiled model.
    data : list of ExperimentData
        The prepared experiments.
    layout : ParameterLayout
        The layout, with every parameter fixed (its offset holds the values).
    started : float
        `time.perf_counter()` when the request started, for the reported wall time.

    Returns
    -------
    FitResult
        A successful result with the fixed parameters, no covariance, output-error metrics and
        residual analysis, the (estimated) initial states, and traces when requested.
    """
    opts = request.options
    p = np.asarray(layout.offset, dtype=float)
    oem = OutputErrorModel(cm, data, layout, opts)
    x0s, notes = [], []
    for e, d in enumerate(data):
        x0, note = estimate_initial_state(cm, d, p, d.x0_known, opts, d.n, f"experiments[{e}].initial_state")
        x0s.append(x0)
        if note:
            notes.append(f"{d.name}: {note}")
    n_x0 = sum(len(f) for f in oem.free_x0)
    sims = [(oem.numeric_states(e, x0s[e], p), None) for e in range(len(data))]
    outputs = [oem.numeric_outputs(e, xs, p) for e, (xs, _) in enumerate(sims)]
    resid = [y - d.y for d, y in zip(data, outputs)]
    weighted = np.concatenate([(oem.weights[:, None] * r)[d.mask] for d, r in zip(data, resid)])
    ndata = weighted.size
    cost = 0.5 * float(weighted @ weighted)
    aic, bic = information_criteria(2 * cost, ndata, n_x0)
    analyses, rmse, fitp = [], {}, {}
    for j, name in enumerate(cm.outputs):
        segments = []
        for d, r in zip(data, resid):
            ok = np.isfinite(d.y[j]) & np.isfinite(r[j])
            segments.append((d.y[j][ok], r[j][ok], {u: d.u[k][ok] for k, u in enumerate(cm.inputs)}))
        analysis = residual_analysis(name, segments)
        analyses.append(analysis)
        rmse[name], fitp[name] = analysis.rmse, analysis.fit_percent
    traces = None
    if opts.return_traces:
        traces = [ExperimentTrace(
            name=d.name, time=d.t.tolist(),
            simulated={o: y[j].tolist() for j, o in enumerate(cm.outputs)},
            residuals={o: [None if not np.isfinite(v) else float(v) for v in r[j]] for j, o in enumerate(cm.outputs)})
            for d, y, r in zip(data, outputs, resid)]
    message = "every parameter is fixed: the model was simulated, not fitted"
    if n_x0:
        message += " (initial states not given were estimated on each record, parameters fixed)"
    if notes:
        message += "; " + "; ".join(notes)
    return FitResult(
        success=True, status="success", message=message,
        parameters={name: ParameterEstimate(value=value, fixed=True, initial=value)
                    for name, value in layout.fixed.items()},
        confidence_level=opts.confidence_level,
        covariance=None, covariance_note="no free parameter: there is no covariance to estimate",
        correlation=None,
        initial_states={d.name: {s: float(x0s[e][i]) for i, s in enumerate(cm.states)} for e, d in enumerate(data)},
        metrics=FitMetrics(cost=cost, ndata=ndata, nfree=ndata - n_x0, nvarys=n_x0, rmse=rmse,
                           fit_percent=fitp, aic=aic, bic=bic),
        solver=SolverInfo(method=request.method, iterations=0, wall_time_s=time.perf_counter() - started,
                          return_status="Simulation", starts=0),
        residual_analysis=analyses, traces=traces)
