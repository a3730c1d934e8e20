"""Coloured noise or model error? A Hausman test of output error against prediction error.

A coloured residual has two readings: the noise is coloured and the model right (then the HAC
intervals are honest), or the model misses a dynamic and its misfit colours the residual (then
the estimates are biased and no interval fixes that). Output error and prediction error with an
AR(p) noise model fitted to the residual agree under the first reading, and differ under the
second, since whitening weighs the frequencies differently: the test compares the output-error
estimates with one Gauss-Newton step of the prediction-error fit from them, against the
covariance of that difference under the noise model, V_OE − V_GLS (`solvers.inference.noise_model`).
It reads the fit's own Jacobian and residual: a few products of matrices, no refit.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from greyfit.schemas.fit import FitWarning
from greyfit.solvers.inference.covariance import CovarianceEstimate
from greyfit.solvers.inference.noise_model import autocovariance, chi2_sf, coloured_meat, fit_ar, whiten

LEVEL = 0.01         # for the two tests together (Bonferroni: each at half of it)
EXCESS_MIN = 0.05    # directions where the noise model gains < 5 % of output error's variance are not tested
WIDENED = 2.0        # HAC standard error over the classical one from which the result says so
MIN_ROWS = 50


@dataclass
class NoiseModelTest:
    """The Hausman statistic, its degrees of freedom and p-value, the AR orders, and each tested
    parameter's shift under the noise model in output error's standard errors; and the segment test
    (the two halves of each record estimating the same parameters) under the same noise model."""

    statistic: float
    dof: int
    p_value: float
    orders: list[int]
    shifts: dict[str, float]
    segment_statistic: float = 0.0
    segment_p_value: float = 1.0


def _series(groups: np.ndarray, sample_keys: np.ndarray, experiment_keys: np.ndarray) -> list[np.ndarray]:
    """Row indices of each (experiment, channel) series in time order."""
    out = []
    order = np.lexsort((sample_keys, groups, experiment_keys))   # by record, channel, then time
    key = experiment_keys[order] * (int(groups.max(initial=0)) + 1) + groups[order]
    for rows in np.split(order, np.flatnonzero(np.diff(key)) + 1):
        if rows.size >= MIN_ROWS:
            out.append(rows)
    return out


def noise_model_test(jac: np.ndarray, res: np.ndarray, groups: np.ndarray, sample_keys: np.ndarray,
                     experiment_keys: np.ndarray, labels: list[str | None]) -> NoiseModelTest | None:
    """Output error against one prediction-error step with a per-series AR noise model.

    Parameters
    ----------
    jac : numpy.ndarray
        Weighted residual Jacobian at the output-error estimates, kept columns only, shape (n, k).
    res : numpy.ndarray
        Weighted residual, shape (n,).
    groups, sample_keys, experiment_keys : numpy.ndarray
        Per row, its channel, sample and experiment.
    labels : list of str
        Name of each column; the test covers the columns named here that are parameters (the rest
        are nuisance columns, e.g. initial states, given as None).

    Returns
    -------
    NoiseModelTest or None
        None where no series is long enough or the matrices are singular.
    """
    k = jac.shape[1]
    info, meat, gls, grad, first = (np.zeros((k, k)), np.zeros((k, k)), np.zeros((k, k)), np.zeros(k), np.zeros((k, k)))
    series = _series(groups, sample_keys, experiment_keys)
    if not series:
        return None
    models = []
    for rows in series:
        j, r = jac[rows], res[rows]
        a, variance = fit_ar(r)
        models.append((rows, a, autocovariance(a, variance)))
        jw, rw = whiten(j, a), whiten(r, a)
        info += j.T @ j
        first += j[:rows.size // 2].T @ j[:rows.size // 2]
        meat += coloured_meat(j, models[-1][2])
        gls += jw.T @ jw / variance
        grad += jw.T @ rw / variance
    try:
        info_inv, gls_inv = np.linalg.inv(info), np.linalg.inv(gls)
    except np.linalg.LinAlgError:
        return None
    step = -gls_inv @ grad
    v_oe = info_inv @ meat @ info_inv
    tested = [i for i, lab in enumerate(labels) if lab is not None]
    test = _hausman(step[tested], v_oe[np.ix_(tested, tested)], (v_oe - gls_inv)[np.ix_(tested, tested)],
                    [labels[i] for i in tested], [a.size - 1 for _, a, _ in models])
    if test is not None:
        test.segment_statistic, test.segment_p_value = _segments(jac, res, models, info_inv, first, info, tested)
    return test


def _segments(jac: np.ndarray, res: np.ndarray, models: list, info_inv: np.ndarray, first: np.ndarray,
              info: np.ndarray, tested: list[int]) -> tuple[float, float]:
    """Do the two halves of the records estimate the same parameters? The score of the first halves,
    g = J₁ᵀr₁ (the second's is −g at the optimum), against its covariance under the noise model:
    g = Bv with the rows of B J_t I⁻¹I₂ in the first halves and −J_t I⁻¹I₁ in the second (I = I₁ + I₂)."""
    g, var = np.zeros(jac.shape[1]), np.zeros((jac.shape[1],) * 2)
    to_first, to_second = info_inv @ (info - first), info_inv @ first
    for rows, _, gamma in models:
        half = rows.size // 2
        j = jac[rows]
        g += j[:half].T @ res[rows[:half]]
        signed = np.vstack([j[:half] @ to_first, -j[half:] @ to_second])
        var += coloured_meat(signed, gamma)
    # the parameters only: an initial state is learnt from the first half alone, and its score compares nothing
    g, var = g[tested], var[np.ix_(tested, tested)]
    try:
        stat = float(g @ np.linalg.solve(var, g))
    except np.linalg.LinAlgError:
        return 0.0, 1.0
    return stat, chi2_sf(stat, g.size)


def _hausman(d: np.ndarray, v_oe: np.ndarray, v_d: np.ndarray, names: list, orders: list[int]):
    """dᵀ V_d⁺ d over the directions where V_d is at least `EXCESS_MIN` of V_OE."""
    try:
        chol = np.linalg.cholesky(v_oe)
        z = np.linalg.solve(chol, d)
        k = np.linalg.solve(chol, np.linalg.solve(chol, v_d).T)
        if not (np.all(np.isfinite(z)) and np.all(np.isfinite(k))):
            return None   # a covariance too ill-conditioned to whiten by: no test, not a failed fit
        lam, u = np.linalg.eigh(0.5 * (k + k.T))
    except np.linalg.LinAlgError:
        return None
    keep = lam > EXCESS_MIN
    stat = float(np.sum((u[:, keep].T @ z) ** 2 / lam[keep])) if keep.any() else 0.0
    dof = int(keep.sum())
    shifts = {n: float(d[i] / math.sqrt(v_oe[i, i])) for i, n in enumerate(names)}
    return NoiseModelTest(stat, dof, chi2_sf(stat, dof) if dof else 1.0, orders, shifts)


def colour_warnings(test: NoiseModelTest | None, cov: CovarianceEstimate) -> list[FitWarning]:
    """`noise_model_disagrees` (suspect) where the test rejects; `residual_coloured` (information)
    where the HAC intervals are `WIDENED` or more times the classical ones and the test does not
    reject, saying what the data cannot tell apart.

    Parameters
    ----------
    test : NoiseModelTest or None
        The test, or None where it did not run.
    cov : CovarianceEstimate
        The fit's covariance (HAC where the residual is coloured).

    Returns
    -------
    list of FitWarning
        At most one warning.
    """
    if test is not None and min(test.p_value, test.segment_p_value) < LEVEL / 2:
        worst = sorted(test.shifts.items(), key=lambda kv: -abs(kv[1]))[:3]
        moved = ", ".join(f"{n} by {s:+.1f} se" for n, s in worst)
        return [FitWarning(
            code="noise_model_disagrees",
            message=f"the residual is coloured, and not by noise alone: refitted with an AR noise model "
                    f"(prediction error, orders {sorted(set(test.orders))}) the estimates move ({moved}) by more "
                    f"than coloured noise explains (Hausman test, χ²({test.dof}) = {test.statistic:.1f}, "
                    f"p = {test.p_value:.1g}; the two halves of the record against each other, p = "
                    f"{test.segment_p_value:.1g}): a dynamic is missing from the model (a sensor or input lag, "
                    "an extra pole, a nonlinearity) and the estimates are biased",
            detail={"test": "Hausman, output error against prediction error", "statistic": test.statistic,
                    "dof": test.dof, "p_value": test.p_value, "segment_p_value": test.segment_p_value,
                    "level": LEVEL, "shifts": test.shifts})]
    widened = max((cov.stderr[n] / cov.classical_stderr[n] for n in cov.stderr
                   if cov.classical_stderr.get(n)), default=1.0) if cov.robust_bandwidth is not None else 1.0
    if widened < WIDENED:
        return []
    said = "" if test is None else (f"; the estimates do not move under an AR noise model (Hausman test, "
                                    f"p = {test.p_value:.2g}), as coloured noise would have it, but a model "
                                    "error that the noise model absorbs cannot be excluded")
    return [FitWarning(
        code="residual_coloured",
        message=f"the residual is coloured: the intervals are the HAC ones, {widened:.1f}× the white-noise "
                "intervals; from these data alone coloured noise cannot be told from a model error whose "
                f"misfit colours the residual{said}",
        detail={"widening": widened, "p_value": None if test is None else test.p_value})]


NEGLIGIBLE_FIT = 99.9   # fit % of every output above which the residual is the integrator's, not noise


def negligible_fit(analyses: list) -> bool:
    """Every output fitted to 99.9 % or better (`lack_of_fit.negligible_residual`'s threshold): the
    residual is not noise, and neither its colour nor its dependence on the inputs says the model is wrong.

    Parameters
    ----------
    analyses : list of ResidualAnalysis
        The fit's residual analyses.

    Returns
    -------
    bool
        True when there is an analysis and every fit % is at least `NEGLIGIBLE_FIT`.
    """
    return bool(analyses) and all((a.fit_percent or 0.0) >= NEGLIGIBLE_FIT for a in analyses)


def coloured_residual_warnings(jac: np.ndarray, res: np.ndarray, groups: np.ndarray | None, keep: np.ndarray,
                               labels: list[str], n_params: int, sample_keys: np.ndarray,
                               experiment_keys: np.ndarray, cov: CovarianceEstimate) -> list[FitWarning]:
    """`colour_warnings` of the `noise_model_test` on a fit's Jacobian (all its columns given).

    Parameters
    ----------
    jac, res : numpy.ndarray
        The fit's weighted residual Jacobian (every column) and residual.
    groups : numpy.ndarray or None
        Per row, its channel (None: one channel).
    keep : numpy.ndarray
        Which columns are free (not on a bound).
    labels : list of str
        Name of every column.
    n_params : int
        Number of leading columns that are parameters.
    sample_keys, experiment_keys : numpy.ndarray
        Per row, its sample and experiment.
    cov : CovarianceEstimate
        The fit's covariance.

    Returns
    -------
    list of FitWarning
        As `colour_warnings`.
    """
    cols = np.flatnonzero(keep)
    names = [labels[c] if c < n_params else None for c in cols]
    channel = np.zeros(res.size, dtype=int) if groups is None else groups
    with np.errstate(over="ignore", invalid="ignore"):
        ok = bool(np.all(np.isfinite(jac[:, cols])) and np.all(np.isfinite(res)))
    test = noise_model_test(jac[:, cols], res, channel, sample_keys, experiment_keys, names) if ok else None
    return colour_warnings(test, cov)
