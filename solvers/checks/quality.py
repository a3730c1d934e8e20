"""Is the answer trustworthy? Checks after the fit, the `quality` verdict and a finite result.

`success` means converged AND sane: any warning whose code is in SUSPECT_CODES makes the
result `suspect` (success false), any in FAILED_CODES makes it `failed`; the other codes inform.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from greyfit.schemas.fit import FitResult, FitWarning
from greyfit.solvers.inference.covariance import CovarianceEstimate, combination, null_directions
from greyfit.solvers.methods.registry import has_shooting_nodes, method_family

FAILED_CODES = {"not_converged", "non_finite_cost", "simulation_failed"}
SUSPECT_CODES = {"fit_below_noise_level", "continuity_gap", "extreme_state", "parameter_uncertain",
                 "hessian_singular", "flat_cost", "residual_far_from_white", "poor_excitation",
                 "multiple_optima",   # solvers/methods/multistart.py
                 # lack of fit and integration (issue 22): each points at a wrong answer
                 "missing_effect_likely", "residual_above_noise", "validation_misfit",
                 "input_held_fitted_linear", "input_faster_than_sampling", "integration_step_coarse",
                 # misspecification tests that need not name the effect (issue 38)
                 "residual_correlated_with_input", "noise_model_disagrees"}
# online, frequency and equation-error checks (solvers/methods/online/checks.py, solvers/frequency/checks.py,
# solvers/methods/equation_error_bias.py) whose warnings count against `good`
SUSPECT_CODES |= {"estimate_outside_bounds", "estimate_at_bound", "closed_loop_unstable", "errors_in_variables_bias",
                  "estimate_not_settled"}
INFO_CODES = {"residual_not_white", "parameter_at_bound", "constraint_active", "input_not_exciting",
              "initial_simulation_diverged", "robust_covariance", "poor_excitation_at_start",
              "lack_of_fit_not_screened", "residual_coloured",
              "singular_derivative_guarded",     # solvers/model/compiler.py
              "polished_with_exact_hessian"}     # solvers/methods/multistart.py

NOISE_FLOOR_RATIO = 5.0      # rmse this many times the data's own noise estimate ...
NOISE_FLOOR_POINTS = 20.0    # ... and the fit % this many points below what that noise allows
GAP_RATIO = 2.0              # simulated cost vs the multiple-shooting optimum
STATE_RATIO = 1e3            # fitted state magnitude vs the simulation at the initial guess
NEAR_SINGULAR = 1e8          # condition of the equilibrated information matrix
FLAT_RELATIVE = 1e-6         # cost change for a 100 % step along a direction, relative to the cost
FAR_FROM_WHITE = 0.95        # residual autocorrelation at some lag
NEGLIGIBLE_FIT = 99.0        # fit % above which the residual's colour does not matter
INDEPENDENCE_NEGLIGIBLE_FIT = 99.9   # ... and its dependence on the inputs (lack_of_fit.negligible_residual)


@dataclass
class QualityInputs:
    """What the checks need from `fit_model`; arrays in the solver's scaled units."""

    converged: bool
    status: str
    cost: float                        # from the re-simulated (reported) residual
    nlp_cost: float                    # the optimiser's own objective
    method: str
    covariance: CovarianceEstimate
    jac: np.ndarray                    # weighted residual Jacobian, kept columns only
    jac_labels: list[str]
    measured: dict[str, list[np.ndarray]] = field(default_factory=dict)   # per output channel
    fitted_state_peak: np.ndarray | None = None     # max |x(t)| per state at the solution
    guess_state_peak: np.ndarray | None = None      # max |x(t)| per state at the initial guess
    state_names: list[str] = field(default_factory=list)
    simulation_failures: list[str] = field(default_factory=list)
    before: list[FitWarning] = field(default_factory=list)
    active_constraints: list[str] = field(default_factory=list)
    sign_constrained: set[str] = field(default_factory=set)   # bounded to one sign (e.g. lower 0)


def noise_level(y: np.ndarray) -> float:
    """Measurement-noise std from second differences, var(Δ²e) = 6σ² for white noise.

    A smooth signal adds little to Δ²y when it is sampled finely, so this bounds from above the
    white-noise part of the data; no model is needed.

    Parameters
    ----------
    y : numpy.ndarray
        A measured series, NaN where missing, shape (N,).

    Returns
    -------
    float
        √(mean(Δ²y²)/6) over the finite samples (taken in order, gaps closed); NaN with fewer than 5.
    """
    y = y[np.isfinite(y)]
    if y.size < 5:
        return math.nan
    return float(np.sqrt(np.mean(np.diff(y, 2) ** 2) / 6.0))


def _fit_warnings(result: FitResult, q: QualityInputs) -> list[FitWarning]:
    out: list[FitWarning] = []
    if method_family(q.method) == "equation_error":
        return out   # channels are derivatives, smoothed: their differences do not show the noise
    for name, series in q.measured.items():
        rmse = result.metrics.rmse.get(name)
        fit = result.metrics.fit_percent.get(name)
        if rmse is None or fit is None or not series:
            continue
        sigma = float(np.sqrt(np.mean([noise_level(s) ** 2 for s in series])))
        y = np.concatenate([s[np.isfinite(s)] for s in series])
        spread = float(np.std(y))
        if not (np.isfinite(sigma) and spread > 0):
            continue
        allowed = 100.0 * (1.0 - sigma / spread)
        if rmse > NOISE_FLOOR_RATIO * sigma and fit < allowed - NOISE_FLOOR_POINTS:
            out.append(FitWarning(
                code="fit_below_noise_level",
                message=f"output '{name}': fit {fit:.1f} % where the data's noise (σ ≈ {sigma:.3g}) "
                        f"allows about {allowed:.1f} %; the model does not explain the data (wrong "
                        "structure, a local minimum, or a degenerate multiple-shooting point)",
                detail={"output": name, "fit_percent": fit, "noise_std": sigma,
                        "achievable_fit_percent": allowed, "rmse": rmse}))
    return out


def _solution_warnings(result: FitResult, q: QualityInputs) -> list[FitWarning]:
    out = []
    if has_shooting_nodes(q.method) and np.isfinite(q.cost) and np.isfinite(q.nlp_cost) \
            and q.cost > GAP_RATIO * q.nlp_cost + 1e-12:
        out.append(FitWarning(
            code="continuity_gap",
            message=f"simulating the fitted model from its initial state gives cost {q.cost:.4g}, "
                    f"the multiple-shooting optimum {q.nlp_cost:.4g}: the trajectory pieces do not "
                    "join into one simulation; try single_shooting from this result",
            detail={"simulated_cost": q.cost, "shooting_cost": q.nlp_cost}))
    if q.fitted_state_peak is not None and q.guess_state_peak is not None:
        for i, s in enumerate(q.state_names):
            ref = max(float(q.guess_state_peak[i]), 1e-12)
            peak = float(q.fitted_state_peak[i])
            if np.isfinite(peak) and peak > STATE_RATIO * ref:
                out.append(FitWarning(
                    code="extreme_state",
                    message=f"state '{s}' reaches {peak:.3g} in the fitted simulation, {peak / ref:.0e} "
                            f"times its size at the initial guess ({ref:.3g}); an unmeasured state "
                            "wandered off to compensate (a degenerate point)",
                    detail={"state": s, "peak": peak, "peak_at_guess": ref}))
    for label, p in result.parameters.items():
        if p.at_bound:
            out.append(FitWarning(
                code="parameter_at_bound", message=f"'{label}' is on its {p.at_bound} bound",
                detail={"parameter": label, "bound": p.at_bound, "value": p.value}))
        elif p.stderr is not None and p.stderr > abs(p.value) and label in q.sign_constrained:
            out.append(FitWarning(
                code="parameter_uncertain",
                message=f"'{label}' = {p.value:.4g} ± {p.stderr:.3g}: its confidence interval "
                        "spans orders of magnitude and includes zero",
                detail={"parameter": label, "value": p.value, "stderr": p.stderr}))
    for text in q.active_constraints:
        out.append(FitWarning(code="constraint_active", message=f"constraint '{text}' is active",
                              detail={"constraint": text}))
    return out


def _curvature_warnings(q: QualityInputs) -> list[FitWarning]:
    out = []
    cov = q.covariance
    if cov.condition is not None and (cov.matrix is None or cov.condition > NEAR_SINGULAR):
        nulls = cov.null_directions
        if not nulls and q.jac.size:
            with np.errstate(over="ignore"):
                norms = np.linalg.norm(q.jac, axis=0)
            d = np.where(norms > 0, norms, 1.0)
            # columns of unit length (a Gram that cannot overflow), where their lengths are finite
            unit = _gram(q.jac / d) if np.all(np.isfinite(norms)) else None
            if unit is not None:
                eigval, eigvec = np.linalg.eigh(unit)
                nulls = null_directions(eigval, eigvec, q.jac_labels, NEAR_SINGULAR)
        out.append(FitWarning(
            code="hessian_singular",
            message=f"the information matrix is (nearly) singular (condition {cov.condition:.1e}); "
                    f"poorly determined: {'; '.join(nulls)}",
            detail={"condition": cov.condition, "null_directions": nulls}))
    gram = _gram(q.jac) if q.jac.size and np.isfinite(q.cost) else None
    if gram is not None:
        eigval, eigvec = np.linalg.eigh(gram)
        floor = FLAT_RELATIVE * max(2 * q.cost, 1e-10 * max(float(eigval[-1]), 1e-300))
        flat = [k for k in range(eigval.size) if eigval[k] <= floor]
        if flat:
            dirs = [combination(eigvec[:, k], q.jac_labels) for k in flat]
            out.append(FitWarning(
                code="flat_cost",
                message="the cost hardly changes (relative < 1e-6) when these combinations change "
                        f"by 100 %: {'; '.join(dirs)}; the optimiser stopped on a plateau, not at a "
                        "determined value",
                detail={"directions": dirs}))
    return out


def _gram(jac: np.ndarray) -> np.ndarray | None:
    """JᵀJ, or None where it is not finite: a fit stopped far from its optimum can have a finite J
    whose products overflow (the coupled tanks from a rough start), and LAPACK's eigensolver then
    raised out of the fit instead of the fit saying what it is."""
    if not np.all(np.isfinite(jac)):
        return None
    with np.errstate(over="ignore", invalid="ignore"):
        gram = jac.T @ jac
    return gram if np.all(np.isfinite(gram)) else None


def _residual_warnings(result: FitResult) -> list[FitWarning]:
    out = []
    for a in result.residual_analysis:
        if a.whiteness.lags and not a.whiteness.passed:
            # a residual that is a negligible part of the signal (noise-free data) may be coloured
            far = a.whiteness.max_abs > FAR_FROM_WHITE and (a.fit_percent or 0.0) < NEGLIGIBLE_FIT
            out.append(FitWarning(
                code="residual_far_from_white" if far else "residual_not_white",
                message=f"residual of '{a.output}' is {'far from ' if far else 'not '}white (max "
                        f"|autocorrelation| {a.whiteness.max_abs:.2f}, band {a.whiteness.bound:.3f}): "
                        "unmodelled dynamics or coloured noise"
                        + ("" if not far else "; the estimates may be biased"),
                detail={"output": a.output, "max_abs": a.whiteness.max_abs, "bound": a.whiteness.bound}))
    return out


def independence_warnings(result: FitResult) -> list[FitWarning]:
    """The residual–input independence test in the verdict (`verdict.review_fit` asks it of output error
    of ODE models): a right model's residual (the noise, coloured or
    not) does not depend on the inputs, whatever the colour (the band allows for it, Bartlett's factor);
    a misread input, a sensor or input lag or a missing pole leave a residual that does. Not on a
    residual that is a negligible part of the signal (noise-free data: the integrator's own error).

    Parameters
    ----------
    result : FitResult
        The fit (its residual analysis per record and output).

    Returns
    -------
    list of FitWarning
        `residual_correlated_with_input` where the test rejects; else empty.
    """
    out = []
    for a in result.residual_analysis:
        if (a.fit_percent or 0.0) >= INDEPENDENCE_NEGLIGIBLE_FIT:
            continue
        for u, test in a.independence.items():
            if test.lags and not test.passed:
                out.append(FitWarning(
                    code="residual_correlated_with_input",
                    message=f"the residual of '{a.output}' is correlated with input '{u}' (max |cross-correlation| "
                            f"{test.max_abs:.2f}, band {test.bound:.3f}, p = {test.p_value:.1g}): the model's response "
                            "to the input is wrong (a misread input, a sensor or input lag, a missing pole or "
                            "nonlinearity), not the noise; the estimates are biased",
                    detail={"output": a.output, "input": u, "max_abs": test.max_abs, "bound": test.bound,
                            "p_value": test.p_value}))
    return out


def _at_start_only(w: FitWarning) -> FitWarning:
    """A start far from the answer can be poorly excited where the answer is not: when the
    information matrix at the solution is well conditioned (no `hessian_singular`, `flat_cost`),
    the warning from before the fit informs and does not make the result suspect (seed 001's closed
    loop from a start at 0.3x the truth reached the truth and was called suspect for it)."""
    return FitWarning(code="poor_excitation_at_start",
                      message=w.message + " (at the initial guess only: at the solution the information "
                                          "matrix is well conditioned)", detail=w.detail)


def assess_fit(result: FitResult, q: QualityInputs) -> FitResult:
    """Attach warnings and the quality verdict; `success` becomes converged and good.

    Parameters
    ----------
    result : FitResult
        The fit's result before the checks.
    q : QualityInputs
        What the checks need from the fit (convergence, costs, covariance, Jacobian, measured series,
        state peaks, simulation failures, warnings from before the fit, active constraints).

    Returns
    -------
    FitResult
        A copy with the warnings, `quality`, `success`, `status` and (when suspect) the message set,
        and every NaN/inf replaced by null.
    """
    warnings = list(q.before)
    if not q.converged:
        message = result.message
        if result.solver.starts <= 1 and any(w.code == "initial_simulation_diverged" for w in q.before):
            # a rough start the solver could not leave (fuzzed: a tank's outflow 300× its value,
            # failed by every method from it, found from 8 starts)
            message += ("; the start guess's simulation or sensitivities diverge: a start nearer the "
                        "data, or several starts (options.multistart, e.g. 8), may reach the optimum")
        warnings.append(FitWarning(code="not_converged", message=message,
                                   detail={"return_status": q.status}))
    for reason in q.simulation_failures:
        warnings.append(FitWarning(code="simulation_failed", message=reason, detail={}))
    if not np.isfinite(q.cost):
        warnings.append(FitWarning(code="non_finite_cost",
                                   message="the cost is not finite at the result (the simulation "
                                           "overflowed or failed); the estimates are not usable",
                                   detail={}))
    else:
        warnings += _fit_warnings(result, q) + _solution_warnings(result, q)
        curvature = _curvature_warnings(q)
        warnings += curvature + _residual_warnings(result)
        if q.covariance.matrix is not None and not curvature:
            warnings = [_at_start_only(w) if w.code == "poor_excitation" else w for w in warnings]
    if q.covariance.robust_bandwidth is not None:
        warnings.append(FitWarning(code="robust_covariance", message=q.covariance.note or "",
                                   detail={"bandwidth": q.covariance.robust_bandwidth}))
    return finite_result(result.model_copy(update=verdict(result.message, warnings, q.converged)))


def verdict(message: str, warnings: list[FitWarning], converged: bool) -> dict:
    """The fields of a result that follow from its warnings: quality, success, status, message.

    Parameters
    ----------
    message : str
        The result's message; for a converged suspect result the suspect codes are appended (an
        earlier suffix replaced).
    warnings : list of FitWarning
        All the result's warnings.
    converged : bool
        Whether the optimiser converged.

    Returns
    -------
    dict
        Update for `FitResult.model_copy`: `warnings`, `quality` (``failed`` for a code in
        `FAILED_CODES`, else ``suspect`` for one in `SUSPECT_CODES`, else ``good``), `success`,
        `status` and, when suspect and converged, `message`.
    """
    codes = {w.code for w in warnings}
    quality = "failed" if codes & FAILED_CODES else "suspect" if codes & SUSPECT_CODES else "good"
    update = {"warnings": warnings, "quality": quality, "success": quality == "good",
              "status": {"good": "success", "suspect": "suspect", "failed": "failed"}[quality]}
    if quality == "suspect" and converged:
        update["message"] = message.split("; but the result is suspect: ")[0] + \
            "; but the result is suspect: " + "; ".join(sorted(codes & SUSPECT_CODES))
    return update


def requalify(result: FitResult, more: list[FitWarning]) -> FitResult:
    """The result with `more` warnings added and its verdict recomputed (checks run after `assess_fit`).

    Parameters
    ----------
    result : FitResult
        A result already assessed.
    more : list of FitWarning
        Warnings from later checks.

    Returns
    -------
    FitResult
        A copy with the warnings appended and the verdict recomputed; `result` itself when `more` is
        empty.
    """
    if not more:
        return result
    converged = not any(w.code == "not_converged" for w in result.warnings)
    return result.model_copy(update=verdict(result.message, list(result.warnings) + more, converged))


def _plain(value):
    """numpy scalars and arrays in free-form fields (warning details) as JSON values."""
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not a JSON value")


def finite_result(result: FitResult) -> FitResult:
    """The result with every NaN/inf replaced by null (JSON has neither; the schema allows null
    exactly where a value can be undefined): pydantic writes them as null, and reading the text
    back is one pass in its Rust core instead of a walk over every number in Python.

    Parameters
    ----------
    result : FitResult
        A result that may hold NaN or inf.

    Returns
    -------
    FitResult
        A new result read back from its JSON.
    """
    return FitResult.model_validate_json(result.model_dump_json(fallback=_plain))
