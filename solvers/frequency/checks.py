"""The trust checks of time-domain fits, for frequency-response fits, and the `quality` verdict.

Before, a frequency fit was `success` whenever Ipopt said so and the loop was stable: from the
plain Levy estimate of the frequency-data course notes (clipped into the box) the fit ended with
a3 on its upper bound, a1..a3 up to 70 times off and a fit of 9 %, `success: true`, `good`. Now
the same verdict as `solvers.checks.quality.assess_fit` (convergence, identifiability: singular
or flat information, parameters uncertain), plus what only a frequency fit knows:

* **fit level**: the scatter of ln G between neighbouring frequencies (linear interpolation in
  log ω, robust median) bounds the data's noise from above; a fitted ln(Ĝ/G) much larger than it
  means the model does not explain the data (`fit_below_noise_level`);
* **parameters at bounds**: a frequency fit's box is its own (not a physical sign), and an
  estimate on it is set by the box, not by the data (`estimate_at_bound`, suspect);
* **an unstable fitted loop** when stability is enforced or penalised (`closed_loop_unstable`).
"""
from __future__ import annotations

import numpy as np

from greyfit.schemas.fit import FitResult, FitWarning
from greyfit.schemas.frequency import FrequencyResponseResult
from greyfit.solvers.checks.quality import QualityInputs, assess_fit
from greyfit.solvers.frequency.data import FrequencySet
from greyfit.solvers.inference.covariance import CovarianceEstimate
from greyfit.solvers.model.parameters import ParameterLayout

NOISE_RATIO = 5.0          # fitted log-residual RMS this many times the data's scatter bound ...
MIN_POINTS = 6             # ... estimated from at least this many interior frequencies
AT_BOUND = "estimate_at_bound"            # both in quality.SUSPECT_CODES
UNSTABLE = "closed_loop_unstable"


def log_scatter(omega: np.ndarray, g: np.ndarray) -> float:
    """Noise std of ln G per component, from each point's distance to the line through its neighbours.

    Linear interpolation in log ω of ln|G| and the unwrapped phase; for white noise of std σ on each
    component the residual has std σ·sqrt(1 + w₋² + w₊²). The median makes the few points at a sharp
    feature (a lightly damped zero) harmless; a smooth response adds curvature, so this is an upper
    bound of the noise. NaN with too few points.

    Parameters
    ----------
    omega : numpy.ndarray
        (N,) angular frequencies, rad/s, increasing.
    g : numpy.ndarray
        (N,) complex response; points that are not finite or zero are left out.

    Returns
    -------
    float
        Robust (median-based) std of ln G per component; NaN with fewer than `MIN_POINTS` + 2 points.
    """
    ok = np.isfinite(g) & (np.abs(g) > 0)
    omega, g = omega[ok], g[ok]
    if omega.size < MIN_POINTS + 2:
        return float("nan")
    x = np.log(omega)
    lg = np.log(np.abs(g)) + 1j * np.unwrap(np.angle(g))
    h0, h1 = x[1:-1] - x[:-2], x[2:] - x[1:-1]
    w_lo, w_hi = h1 / (h0 + h1), h0 / (h0 + h1)
    resid = lg[1:-1] - (w_lo * lg[:-2] + w_hi * lg[2:])
    norm = np.sqrt(1 + w_lo ** 2 + w_hi ** 2)
    parts = np.concatenate([np.abs(resid.real) / norm, np.abs(resid.imag) / norm])
    return float(np.median(parts) / 0.6745)


def fit_level_warnings(result: FitResult, response: FrequencyResponseResult,
                       sets: list[FrequencySet]) -> list[FitWarning]:
    """`fit_below_noise_level` for each data set whose ln(Ĝ/G) is far above the data's scatter.

    Parameters
    ----------
    result : FitResult
        The fit's result (its `metrics.fit_percent` goes into the detail).
    response : FrequencyResponseResult
        The fitted responses per data set.
    sets : list of FrequencySet
        The measured data sets.

    Returns
    -------
    list of FitWarning
        One warning per set whose RMS of ln(Ĝ/G) exceeds `NOISE_RATIO` times its `log_scatter`; sets
        whose scatter cannot be estimated are skipped.
    """
    out: list[FitWarning] = []
    fitted = {d.name: np.array(d.fitted_real) + 1j * np.array(d.fitted_imag) for d in response.data}
    for s in sets:
        g_hat = fitted[s.name]
        sigma = log_scatter(s.omega, s.response)
        ok = np.isfinite(g_hat) & (np.abs(g_hat) > 0) & (np.abs(s.response) > 0)
        if not np.isfinite(sigma) or not np.any(ok):
            continue
        q = np.log(g_hat[ok] / s.response[ok])
        rms = float(np.sqrt(np.mean(np.concatenate([q.real, q.imag]) ** 2)))
        if rms > NOISE_RATIO * sigma:
            out.append(FitWarning(
                code="fit_below_noise_level",
                message=f"data set '{s.name}': the fitted response is off the data by {rms:.3g} in ln G (about "
                        f"{100 * (np.exp(rms) - 1):.0f} %) where the data scatter by at most {sigma:.3g} between "
                        "neighbouring frequencies: the model does not explain the data (a local minimum, a "
                        "parameter held by its bound, or a wrong structure); try the Levy / Sanathanan-Koerner "
                        "start (levy_start, sk_iterations) or multistart",
                detail={"data": s.name, "log_residual_rms": rms, "noise_bound": sigma,
                        "fit_percent": result.metrics.fit_percent.get(s.name)}))
    return out


def bound_warnings(result: FitResult) -> list[FitWarning]:
    """`estimate_at_bound` for each parameter that ended on a bound of its box.

    Parameters
    ----------
    result : FitResult
        The fit's result; a parameter's `at_bound` says which bound it ended on.

    Returns
    -------
    list of FitWarning
        One warning per parameter at a bound, naming it, the bound and the value.
    """
    out: list[FitWarning] = []
    for label, p in result.parameters.items():
        if p.at_bound:
            out.append(FitWarning(
                code=AT_BOUND,
                message=f"'{label}' = {p.value:.4g} ends on its {p.at_bound} bound: the estimate is set by the "
                        "bound, not by the data, and has no standard error; widen the bound if it is not "
                        "physical, or start elsewhere (the Levy start, multistart)",
                detail={"parameter": label, "bound": p.at_bound, "value": p.value}))
    return out


def assess_frequency_fit(result: FitResult, *, sets: list[FrequencySet], layout: ParameterLayout,
                         theta_s: np.ndarray, converged: bool, status: str, nlp_cost: float,
                         covariance: CovarianceEstimate, jac: np.ndarray, keep: np.ndarray,
                         stability_enforced: bool, before: list[FitWarning] | None = None) -> FitResult:
    """The quality verdict of a frequency fit: `assess_fit`'s checks plus the frequency ones.

    Parameters
    ----------
    result : FitResult
        The fit's result before the checks.
    sets : list of FrequencySet
        The measured data sets.
    layout : ParameterLayout
        The free parameters (labels, bounds: a box that excludes a sign marks the parameter signed).
    theta_s : numpy.ndarray
        (nθ,) estimate in scaled parameters.
    converged : bool
        Whether the solver converged.
    status : str
        The solver's return status.
    nlp_cost : float
        The NLP's cost at the estimate.
    covariance : CovarianceEstimate
        The covariance estimate (or the reason it is unavailable).
    jac : numpy.ndarray
        Data-residual Jacobian in scaled parameters (all columns).
    keep : numpy.ndarray
        (nθ,) booleans: the columns not at a bound.
    stability_enforced : bool
        Whether an unstable fitted loop is a failure of the fit (routh, penalty).
    before : list of FitWarning, optional
        Warnings found before the checks (the multistart's `multiple_optima`).

    Returns
    -------
    FitResult
        A copy with the warnings of `assess_fit` and the frequency checks and the verdict set; a
        `parameter_at_bound` warning is dropped where `estimate_at_bound` already names the parameter.
    """
    fr = result.frequency_response
    before = list(before or []) + bound_warnings(result) + ([] if fr is None else fit_level_warnings(result, fr, sets))
    if fr is not None and stability_enforced and not fr.stable:
        bad = [lp.setting for lp in fr.loops if not lp.stable]
        before.append(FitWarning(code=UNSTABLE, message=f"the fitted closed loop is unstable for {bad}",
                                 detail={"loops": bad}))
    size = np.maximum(np.abs(theta_s), 1.0)       # columns for a 100 % change of the estimate
    signed = {lab for i, lab in enumerate(layout.labels) if layout.lower[i] >= 0 or layout.upper[i] <= 0}
    q = QualityInputs(converged=converged, status=status,
                      cost=result.metrics.cost if result.metrics.cost is not None else float("nan"),
                      nlp_cost=nlp_cost, method="frequency_response", covariance=covariance,
                      jac=(jac * size)[:, keep], jac_labels=[lab for lab, k in zip(layout.labels, keep) if k],
                      before=before, sign_constrained=signed)
    assessed = assess_fit(result, q)
    # the time-domain check's informative `parameter_at_bound` says again what `estimate_at_bound` says
    held = {w.detail.get("parameter") for w in assessed.warnings if w.code == AT_BOUND}
    kept = [w for w in assessed.warnings if not (w.code == "parameter_at_bound" and w.detail.get("parameter") in held)]
    return assessed.model_copy(update={"warnings": kept})
