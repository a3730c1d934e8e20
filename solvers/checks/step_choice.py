"""RK4 substeps chosen before the fit from the model's fastest local time constant.

The post-fit check (`fit_checks.fastest_rate_warning`) judges the step along the fitted trajectory;
this module makes the same measurement along the simulation at the initial guess and picks the
substeps so that |λ|·h ≤ TARGET_RATE_STEP, half the post-fit threshold (0.5), so that the fit may move
the parameters towards a faster model and still be integrated accurately. Only when the request did
not give `options.substeps`; the choice is reported in `preprocessing.substeps`.
"""
from __future__ import annotations

import math

import numpy as np

from greyfit.schemas.preprocess import PreprocessingReport
from greyfit.solvers.checks.fit_checks import fastest_rate
from greyfit.solvers.checks.simulation import numeric_step
from greyfit.solvers.data.experiments import prepare_experiments
from greyfit.solvers.dynamics.integration import integrator_of
from greyfit.solvers.methods.registry import simulates_outputs
from greyfit.solvers.model.compiler import compile_model
from greyfit.solvers.model.parameters import build_layout

TARGET_RATE_STEP = 0.25
MAX_SUBSTEPS = 100      # the schema's bound on options.substeps


def substeps_for(rate: float, dt: float) -> int:
    """Least RK4 steps per sample interval with |λ|·h ≤ TARGET_RATE_STEP (1 to MAX_SUBSTEPS).

    Parameters
    ----------
    rate : float
        |λ| of the fastest mode, in 1/time unit.
    dt : float
        Sample interval, in the same time unit.

    Returns
    -------
    int
        ceil(|λ| dt / `TARGET_RATE_STEP`) clipped to [1, `MAX_SUBSTEPS`]; 1 for a non-finite or
        non-positive rate.
    """
    if not (math.isfinite(rate) and math.isfinite(dt)) or rate <= 0:
        return 1
    return int(min(max(math.ceil(rate * dt / TARGET_RATE_STEP), 1), MAX_SUBSTEPS))


def _applies(request) -> bool:
    model, opts = request.model, request.options
    return (simulates_outputs(request.method) and integrator_of(opts).fixed_step
            and "substeps" not in opts.model_fields_set
            and model.discrete is None and not any(p.time_varying is not None for p in model.parameters))


def _guess_states(cm, data, layout, options, substeps: int) -> list[np.ndarray]:
    """States at every sample, simulated at the initial guess with `substeps`."""
    step = numeric_step(cm, options.model_copy(update={"substeps": substeps}), sum(d.n for d in data))
    theta_s = layout.initial / layout.scale
    out = []
    for e, d in enumerate(data):
        x0 = np.zeros(cm.nx)
        for i, v in d.x0_known.items():
            x0[i] = v
        for name, state in cm.direct_outputs.items():
            if cm.states.index(state) not in d.x0_known:
                first = d.y[cm.outputs.index(name)]
                first = first[np.isfinite(first)]
                x0[cm.states.index(state)] = first[0] if first.size else 0.0
        p = np.asarray(layout.full(e, theta_s), dtype=float).ravel()
        if d.n < 2:
            out.append(x0[:, None])
            continue
        xs, = step(x0, d.u[:, :-1], d.u[:, 1:], p, d.t[None, :-1], np.diff(d.t)[None, :], n=d.n - 1,
                   accumulate=True)
        out.append(np.hstack([x0[:, None], xs]))
    return out


def choose_substeps(request, report: PreprocessingReport | None):
    """(request with options.substeps chosen, report saying so); unchanged where it does not apply.

    Applies to output-error fits (auto as the shooting method it will run: the steps do not depend
    on which) with a fixed-step integrator (RK4) of continuous models without time-varying
    parameters whose request did not give `options.substeps`.

    Parameters
    ----------
    request : FitRequest
        The prepared fit request.
    report : PreprocessingReport or None
        The preprocessing report so far.

    Returns
    -------
    request : FitRequest
        A copy with the chosen `options.substeps`, or the request itself.
    report : PreprocessingReport or None
        A copy with `substeps` and `substeps_note` set, or the report unchanged.

    Raises
    ------
    ModelDefinitionError, DataError
        When the model does not compile or the experiments do not fit it (as `compile_model`,
        `prepare_experiments`).
    """
    if not _applies(request):
        return request, report
    cm = compile_model(request.model)
    data = prepare_experiments(request.experiments, cm)
    layout = build_layout(request.model, [d.name for d in data])
    if layout.size == 0 or cm.nx == 0:
        return request, report
    states = _guess_states(cm, data, layout, request.options, 1)
    rate, dt = fastest_rate(cm, data, layout, layout.initial / layout.scale, states)
    chosen = substeps_for(rate, dt)
    if chosen > 1:   # re-measure along the accurate simulation (a coarse one can run away)
        states = _guess_states(cm, data, layout, request.options, chosen)
        rate, dt = fastest_rate(cm, data, layout, layout.initial / layout.scale, states)
        chosen = max(chosen, substeps_for(rate, dt))
    note = (f"options.substeps not given: {chosen} RK4 step(s) per sample interval, from the model's fastest "
            f"mode along the simulation at the initial guess (|λ| ≈ {rate:.3g} 1/s, Δt = {dt:.3g} s, "
            f"|λ|h = {rate * dt / chosen:.2f} ≤ {TARGET_RATE_STEP})")
    report = report or PreprocessingReport()
    report = report.model_copy(update={"substeps": chosen, "substeps_note": note})
    options = request.options.model_copy(update={"substeps": chosen})
    return request.model_copy(update={"options": options}), report


def substeps_retry(request, result):
    """A request to fit again when the substeps chosen here are coarse along the fitted trajectory.

    The choice is made at the initial guess; a fit that ends at a much faster model (a rough
    guess) is refitted once from its estimates with the substeps the post-fit check suggests.
    None when the request gave its substeps or the step is fine.

    Parameters
    ----------
    request : FitRequest
        The request that was fitted.
    result : FitResult
        Its result, with its warnings and preprocessing report.

    Returns
    -------
    tuple of (FitRequest, PreprocessingReport) or None
        The request started from the estimates (clipped into the bounds) with twice the suggested
        substeps (at least one more, at most `MAX_SUBSTEPS`), and the report saying so; None when the
        substeps were given, the fit was already refitted, the step is not coarse, or the substeps
        are already at `MAX_SUBSTEPS`.
    """
    report = result.preprocessing
    coarse = [w for w in result.warnings if w.code == "integration_step_coarse"]
    if not coarse or report is None or report.substeps is None or report.substeps_note is None \
            or "refitted" in report.substeps_note:
        return None
    need = int(min(max(coarse[0].detail.get("suggested_substeps", 1) * 2, report.substeps + 1), MAX_SUBSTEPS))
    if need <= report.substeps:
        return None
    model = request.model.model_copy(update={"parameters": [at_estimate(p, result) for p in request.model.parameters]})
    options = request.options.model_copy(update={"substeps": need})
    note = (report.substeps_note + f"; at the fitted parameters |λ| ≈ {coarse[0].detail.get('max_rate', 0):.3g} 1/s "
            f"made it coarse, so the fit was refitted from its estimates with {need} substeps")
    retry = request.model_copy(update={"model": model, "options": options})
    return retry, report.model_copy(update={"substeps": need, "substeps_note": note})


def at_estimate(p, result):
    """The parameter `p` started from its estimate in `result` (clipped into its bounds).

    Parameters
    ----------
    p : Parameter
        A parameter of the fitted model.
    result : FitResult
        The fit's result.

    Returns
    -------
    Parameter
        `p` with `value` the estimate; `p` itself when fixed or not estimated.
    """
    est = result.parameters.get(p.name)
    if p.fixed or est is None or not math.isfinite(est.value):
        return p
    lo = -math.inf if p.lower is None else p.lower
    hi = math.inf if p.upper is None else p.upper
    return p.model_copy(update={"value": float(min(max(est.value, lo), hi))})
