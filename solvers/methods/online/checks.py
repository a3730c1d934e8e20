"""Is an online estimate trustworthy? Excitation against the model's needs, and physical pre-images.

Online estimators always return a number. Two ways it can be wrong that the estimator cannot see:

* the input is not persistently exciting of the order the model needs (the model reference
  adaptive systems chapter: an n-th order plant needs at least n frequencies). Measurement noise
  can give the regressor full rank while the input leaves directions undetermined, so the
  estimate wanders off along them (a DC input: L 100 times off; one sine into an RLC circuit:
  negative R and L);
* an estimate with no physical pre-image: the coefficients map back to a parameter outside its
  declared bounds (R < 0), which no physical system has. Online estimators do not enforce bounds,
  so this is marked per sample of θ(t) and, at the final estimate, counts against `good`.

Both give a warning whose code makes the result `suspect` (success false); the verdict itself is
the one of `solvers.checks.quality` (same failed/suspect codes).
"""
from __future__ import annotations

import numpy as np

from greyfit.schemas.fit import FitResult, FitWarning
from greyfit.schemas.online import ExcitationReport
from greyfit.solvers.checks.quality import FAILED_CODES, SUSPECT_CODES
from greyfit.solvers.model.parameters import ParameterLayout

OUTSIDE_BOUNDS = "estimate_outside_bounds"      # in quality.SUSPECT_CODES


def excitation_warnings(excitation: ExcitationReport) -> list[FitWarning]:
    """`poor_excitation` when the regressor is rank deficient or the inputs' PE order is too low.

    Parameters
    ----------
    excitation : ExcitationReport
        The persistent-excitation report of the run (`recursive.excitation_report`).

    Returns
    -------
    list of FitWarning
        Empty when the report says the data are persistently exciting; else one `poor_excitation`
        warning naming the order the model needs, the order the inputs give and the regressor's rank.
    """
    if excitation.persistently_exciting:
        return []
    orders = ", ".join(f"'{u}' of order {k}" for u, k in excitation.input_order.items()) or "no input"
    parts = []
    if excitation.required_order is not None and (excitation.available_order or 0) < excitation.required_order:
        need = excitation.required_order
        parts.append(f"the model needs input persistently exciting of order {need} (at least "
                     f"{(need + 1) // 2} sinusoids of distinct frequencies, or a PRBS), the input gives "
                     f"{orders} over the estimator's window of {excitation.window_samples} samples, so the "
                     f"regressor is rank deficient: the input determines at most {excitation.available_order} "
                     f"of the {need} coefficients of an equation"
                     + (f" (its numerical rank {excitation.regressor_rank} comes from noise)"
                        if excitation.regressor_rank > (excitation.available_order or 0) else ""))
    if excitation.regressor_rank < excitation.regressor_size:
        parts.append(f"the regressor has rank {excitation.regressor_rank} of {excitation.regressor_size}")
    return [FitWarning(
        code="poor_excitation",
        message="not persistently exciting: " + "; ".join(parts) + ". Some parameter combinations are not "
                "determined by these data and the estimate follows noise along them; add excitation "
                "(superpose a small multi-sine or PRBS on the input)",
        detail={"input_order": excitation.input_order, "required_order": excitation.required_order,
                "available_order": excitation.available_order, "regressor_rank": excitation.regressor_rank,
                "regressor_size": excitation.regressor_size, "window_samples": excitation.window_samples})]


def outside_bounds(values: np.ndarray, layout: ParameterLayout) -> np.ndarray:
    """(M, nθ) True where a physical value is outside its declared bounds or not finite.

    Parameters
    ----------
    values : numpy.ndarray
        (M, nθ) physical parameter values, one row per sample (or one row: the final estimate).
    layout : ParameterLayout
        The free parameters; its `lower` and `upper` (nθ,) are the declared bounds.

    Returns
    -------
    numpy.ndarray
        (M, nθ) booleans, True where a value is below its lower bound, above its upper bound or NaN.
    """
    with np.errstate(invalid="ignore"):
        inside = (values >= layout.lower) & (values <= layout.upper)
    return ~inside


def bound_warnings(theta: np.ndarray, layout: ParameterLayout, marks: np.ndarray) -> list[FitWarning]:
    """A warning naming each final estimate outside its bounds, with the share of samples that were.

    Parameters
    ----------
    theta : numpy.ndarray
        (nθ,) final physical estimate.
    layout : ParameterLayout
        The free parameters: labels and declared bounds.
    marks : numpy.ndarray
        (M, nθ) booleans from `outside_bounds` over the kept trajectory samples.

    Returns
    -------
    list of FitWarning
        One `estimate_outside_bounds` warning per parameter whose final estimate is outside its bounds
        (the bound, its limit and the fraction of samples outside in `detail`); empty when all are inside.
    """
    out = []
    final = outside_bounds(theta[None, :], layout)[0]
    for i, label in enumerate(layout.labels):
        if not final[i]:
            continue
        bound = "lower" if theta[i] < layout.lower[i] else "upper"
        limit = float(layout.lower[i] if bound == "lower" else layout.upper[i])
        out.append(FitWarning(
            code=OUTSIDE_BOUNDS,
            message=f"'{label}' = {theta[i]:.4g} is outside its {bound} bound {limit:g}: the estimated "
                    f"coefficients have no physical pre-image ({100 * float(np.mean(marks[:, i])):.0f} % of "
                    "the trajectory samples are outside the bounds; see trajectory.outside_bounds). Online "
                    "estimators do not enforce bounds; check the excitation and the model",
            detail={"parameter": label, "value": float(theta[i]), "bound": bound, "limit": limit,
                    "fraction_of_samples": float(np.mean(marks[:, i]))}))
    return out


def apply_verdict(result: FitResult, warnings: list[FitWarning]) -> FitResult:
    """Attach the warnings and the quality verdict; `success` becomes finite and good.

    Parameters
    ----------
    result : FitResult
        The online estimator's result before the checks.
    warnings : list of FitWarning
        The excitation and bound warnings to attach (a `not_converged` warning is added when
        `result.success` is false: the recursion gave no finite estimate).

    Returns
    -------
    FitResult
        A copy with the warnings appended and `quality` ("good", "suspect" or "failed" by the codes of
        `solvers.checks.quality`), `status`, `success` (quality is "good") and `message` set from it.
    """
    if not result.success:      # the recursion overflowed: no finite estimate
        warnings = warnings + [FitWarning(code="not_converged", message="the online estimate is not finite "
                                          "(the recursion overflowed); check the excitation, the gains and the guess",
                                          detail={"return_status": result.solver.return_status})]
    codes = {w.code for w in warnings}
    quality = "failed" if codes & FAILED_CODES else "suspect" if codes & SUSPECT_CODES else "good"
    message = result.message
    if quality == "suspect":
        message += "; but the result is suspect: " + "; ".join(sorted(codes & SUSPECT_CODES))
    return result.model_copy(update={
        "warnings": list(result.warnings) + warnings, "quality": quality, "success": quality == "good",
        "status": {"good": "success", "suspect": "suspect", "failed": "failed"}[quality], "message": message})
