"""How much reading smooth inputs as linear between samples moves the estimates.

First-order hold is exact only for an input that really ramps between its samples. A physical
input sampled by an instrument is smooth, and on a long quiet record the (ωΔt)²/8 it is misread by
moves the estimates by several standard errors while the fit looks good (a pendulum's damping by 2
standard errors at ω·Δt ≤ 0.2 in the trust benchmark). The samples alone cannot tell a ramp from a
smooth curve, so the check measures what the difference costs: it simulates the fitted model on a
grid four times finer with the inputs read both ways (`solvers.data.refine`: linear and cubic
Hermite; the same integration steps, so only the inputs differ) and turns the difference of the
weighted outputs into the Gauss-Newton step of a refit, Δθ = −(JᵀJ)⁻¹Jᵀδ (J the fit's own), in
standard errors.

Under `auto` (every input smooth), a shift of `REFIT_SHIFT` standard errors or more refits on the
cubic reading (`cubic_retry`, called by `solvers.fit`); a request that forced `foh` asserted ramps
and is taken at its word.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from greyfit.schemas.fit import FitRequest, FitResult, FitWarning
from greyfit.schemas.preprocess import PreprocessingReport
from greyfit.solvers.checks.step_choice import at_estimate
from greyfit.solvers.data.experiments import prepare_experiments
from greyfit.solvers.data.preprocess import held_inputs
from greyfit.solvers.data.refine import (
    DEFAULT_FACTOR,
    MAX_FACTOR,
    cubic_on_finer_grid,
    factor_for,
    linear_on_finer_grid,
    refine_request,
)
from greyfit.solvers.methods.registry import simulates_outputs
from greyfit.solvers.methods.shooting.model import OutputErrorModel, sensitivity_jacobian
from greyfit.solvers.model.compiler import compile_model
from greyfit.solvers.model.parameters import build_layout

# a refit on the cubic reading is worth it from a shift of 0.3 standard errors (coverage of a 95 %
# interval falls to about 94 % there); a forced linear reading is flagged from 0.5 (about 92 %)
REFIT_SHIFT = 0.3
WARN_SHIFT = 0.5
MIN_SAMPLES = 5


@dataclass
class LinearReading:
    """The estimated move of each estimate, in its standard errors, from the cubic reading."""

    shifts: dict[str, float]     # parameter label -> |Δθ| / stderr
    worst: str                   # the label of the largest
    factor: int                  # the refinement that leaves about 0.1 standard errors
    moves: dict[str, float] = field(default_factory=dict)   # label -> the predicted Δθ (physical)

    @property
    def shift(self) -> float:
        """The largest shift, in standard errors.

        Returns
        -------
        float
            ``shifts[worst]``.
        """
        return self.shifts[self.worst]


def _applies(request: FitRequest, result: FitResult) -> bool:
    model = request.model
    return (simulates_outputs(result.solver.method) and request.options.input_interpolation == "foh"
            and bool(model.inputs) and model.discrete is None and request.options.prefilter is None
            and all(p.time_varying is None for p in model.parameters)
            and result.covariance is not None and result.initial_states is not None
            and result.solver.return_status not in ("", None))


def _factor_keeping_step(substeps: int, wanted: int) -> int | None:
    """A refinement whose grid keeps the user's RK4 step exactly: a divisor of `substeps` between
    `DEFAULT_FACTOR` and `MAX_FACTOR`, the least one at or above `wanted`, else the largest; None
    when there is none."""
    divisors = [d for d in range(DEFAULT_FACTOR, MAX_FACTOR + 1) if substeps % d == 0]
    return min([d for d in divisors if d >= wanted], default=max(divisors, default=None))


def linear_reading(request: FitRequest, result: FitResult) -> LinearReading | None:
    """The shift of the estimates that reading the inputs as cubics instead of ramps would bring.

    Parameters
    ----------
    request : FitRequest
        The prepared request that was fitted (interpolation and substeps resolved).
    result : FitResult
        Its result.

    Returns
    -------
    LinearReading or None
        None where the check does not apply (equation error, held inputs, no input, a discrete-time
        model, time-varying parameters, a prefilter, no covariance), a record is too short or its
        inputs incomplete, or a simulation fails.
    """
    if not _applies(request, result):
        return None
    cm = compile_model(request.model)
    data = prepare_experiments(request.experiments, cm)
    if any(d.n < MIN_SAMPLES or not np.all(np.isfinite(d.u)) for d in data):
        return None
    layout = build_layout(request.model, [d.name for d in data])
    try:
        theta = np.array([result.parameters[label].value for label in layout.labels], dtype=float)
        x0s = [result.initial_states[d.name] for d in data]
    except KeyError:
        return None
    theta_s = theta / layout.scale
    options = request.options
    substeps = max(1, math.ceil((options.substeps or 1) / DEFAULT_FACTOR))
    fitted = OutputErrorModel(cm, data, layout, options)
    # the finer grid's step only (its weights and scales are the record's): the outputs are read at
    # the measured samples, where both readings are the record's inputs at the record's times
    stepper = OutputErrorModel(cm, data, layout, options.model_copy(update={"substeps": substeps}))
    # the fit's own Jacobian (its covariance's, asked again) for the step: the finer grid's ramps are
    # the record's, so it is the ramps' Jacobian at the measured samples up to the integration
    # error; the cubics' differs from it in second order only and cost a sensitivity pass of 4× the
    # samples (a fifth of a 40 000-sample fit)
    try:
        jac, _, _ = sensitivity_jacobian(fitted, theta_s, x0s)
        r_cubic, r_linear = _weighted_residuals_on_finer_grid(fitted, stepper, theta_s, x0s, DEFAULT_FACTOR)
    except RuntimeError:
        return None
    delta = r_cubic - r_linear
    if not (np.all(np.isfinite(jac)) and np.all(np.isfinite(delta))):
        return None
    step = -np.linalg.lstsq(jac, delta, rcond=None)[0][:layout.size] * layout.scale
    shifts, moves = {}, {}
    for label, move in zip(layout.labels, step):
        moves[label] = float(move)
        se = result.parameters[label].stderr
        if se is not None and se > 0 and result.parameters[label].at_bound is None:
            shifts[label] = float(abs(move) / se)
    if not shifts:
        return None
    worst = max(shifts, key=lambda k: shifts[k])
    return LinearReading(shifts, worst, factor_for(shifts[worst]), moves)


def _weighted_residuals_on_finer_grid(fitted: OutputErrorModel, stepper: OutputErrorModel, theta_s: np.ndarray,
                                      x0s: list[dict[str, float]], factor: int) -> tuple[np.ndarray, np.ndarray]:
    """Weighted (simulated − measured) at the measured samples with the inputs read as cubics and as
    ramps on the grid `factor` times finer: `stepper`'s step (the finer grid's substeps; raises
    RuntimeError where it fails) integrates,
    the outputs are `fitted`'s at every `factor`-th state (the record's own times and inputs: both
    readings pass through the samples), so nothing of the record's outputs is spread on the finer
    grid. The same numbers as `_weighted_residual` of the finer records, at a quarter of its output
    evaluations and none of its missing-sample arrays."""
    cubic: list[np.ndarray] = []
    linear: list[np.ndarray] = []
    step = stepper.numeric_functions()[0]
    for e, d in enumerate(fitted.data):
        p = np.asarray(fitted.layout.full(e, theta_s), dtype=float).ravel()
        x0 = np.array([x0s[e][s] for s in fitted.cm.states], dtype=float)
        t, u_cubic = cubic_on_finer_grid(d.t, d.u, factor)
        t0, dt = t[None, :-1], np.diff(t)[None, :]
        for u, parts in ((u_cubic, cubic), (linear_on_finer_grid(d.t, d.u, factor), linear)):
            # the step's loop itself, not `numeric_states`: its cache of the last four trajectories
            # keeps the fit's own, which the lack-of-fit screen reads after this check
            xs, = step(x0[:, None], u[:, :-1], u[:, 1:], p, t0, dt, n=t.size - 1, accumulate=True)
            states = np.hstack([x0[:, None], xs[:, factor - 1::factor]])
            y = fitted.numeric_outputs(e, states, p)
            parts.append(((y - d.y) * fitted.weights[:, None]).T[d.mask.T])
    return np.concatenate(cubic), np.concatenate(linear)


def _weighted_residual(oem: OutputErrorModel, theta_s: np.ndarray, x0s: list[dict[str, float]]) -> np.ndarray:
    """Weighted (simulated − measured) at the measured samples, sample-major: the rows of
    `sensitivity_jacobian`'s residual, from a simulation."""
    parts = []
    for e, d in enumerate(oem.data):
        p = np.asarray(oem.layout.full(e, theta_s), dtype=float).ravel()
        x0 = np.array([x0s[e][s] for s in oem.cm.states], dtype=float)
        y = oem.numeric_outputs(e, oem.numeric_states(e, x0, p), p)
        parts.append(((y - d.y) * oem.weights[:, None]).T[d.mask.T])
    return np.concatenate(parts)


def _predicted(p, moves: dict[str, float]):
    """The parameter `p`, started at its estimate, moved by the Gauss-Newton step that the linear
    reading predicted (clipped into its bounds): the refit starts near its optimum. A move that
    would take the start across zero or to less than half its size is not made: the start sets the
    parameter's scale in the solver (`nominal_scale`), and the estimate's is the one to keep."""
    move = moves.get(p.name)
    if p.fixed or move is None or not math.isfinite(move):
        return p
    lo = -math.inf if p.lower is None else p.lower
    hi = math.inf if p.upper is None else p.upper
    value = float(min(max(p.value + move, lo), hi))
    if value * p.value <= 0 or abs(value) < 0.5 * abs(p.value):
        return p
    return p.model_copy(update={"value": value})


def cubic_retry(request: FitRequest, result: FitResult, report: PreprocessingReport | None,
                substeps_given: bool):
    """A request to fit again on the cubic reading of the inputs, where `auto` read them as linear
    and that moved an estimate by `REFIT_SHIFT` standard errors or more.

    Parameters
    ----------
    request : FitRequest
        The prepared request that was fitted.
    result : FitResult
        Its result.
    report : PreprocessingReport or None
        The preprocessing report: only a linear reading that `auto` chose (every input smooth) is
        revisited.
    substeps_given : bool
        Whether the user set `options.substeps`: then the finer grid must keep their step exactly
        (a refinement that divides the substeps), else the shift is reported instead of refitted.

    Returns
    -------
    retry : tuple of (FitRequest, PreprocessingReport) or None
        The request on the finer grid, started from the estimates, and the report saying so.
    warnings : list of FitWarning
        ``input_faster_than_sampling`` where the shift matters but the grid could not be refined.
    """
    if report is None or report.interpolation_note is None or report.input_refinement \
            or any(v != "foh" for v in report.input_interpolation.values()):
        return None, []
    if any(looks for looks, _ in held_inputs(request.experiments).values()):
        return None, []      # mixed held and smooth inputs: one reading serves all (the note says so)
    reading = linear_reading(request, result)
    if reading is None or reading.shift < REFIT_SHIFT:
        return None, []
    substeps = request.options.substeps
    factor = _factor_keeping_step(substeps, reading.factor) if substeps_given else reading.factor
    if factor is None:
        inputs = list(request.model.inputs)
        return None, [FitWarning(
            code="input_faster_than_sampling",
            message=f"read as linear between samples, input(s) {inputs} bias the estimates: a cubic reading of "
                    f"the same samples moves {reading.worst} by {reading.shift:.2g} standard errors, and with "
                    f"options.substeps = {substeps} the record cannot be refitted on a finer grid at the same "
                    f"step (that needs substeps divisible by {DEFAULT_FACTOR}-{MAX_FACTOR}); leave substeps to the "
                    "fit, set input_interpolation to 'cubic', or give the inputs on a finer time grid",
            detail={"inputs": inputs, "parameter": reading.worst, "shift_in_stderr": reading.shift,
                    "shifts": reading.shifts})]
    refined = refine_request(request, factor)
    model = refined.model.model_copy(update={"parameters": [_predicted(at_estimate(p, result), reading.moves)
                                                            for p in refined.model.parameters]})
    note = (f"{report.interpolation_note}; read as linear, they moved {reading.worst} by {reading.shift:.2g} "
            f"standard errors (a cubic reading of the same samples), so the fit was refitted with the inputs read "
            f"as cubics between samples ({factor} points per sample interval)")
    per_input = {name: "cubic" for name in report.input_interpolation}
    new_report = report.model_copy(update={"input_interpolation": per_input, "interpolation_note": note,
                                           "input_refinement": factor})
    return (refined.model_copy(update={"model": model}), new_report), []
