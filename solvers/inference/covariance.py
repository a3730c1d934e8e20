"""Jacobian-based covariance σ²(JᵀJ)⁻¹ with bound handling and identifiability notes."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from greyfit.solvers.inference.noise_model import NoiseModelMeat, noise_model_meat
from greyfit.solvers.inference.robust_covariance import hac_meat
from greyfit.solvers.inference.statistics import student_t_quantile

CONDITION_LIMIT = 1e12
ABSORBED = 1e-8   # share of the noise left in the residual below which it reads no size


@dataclass
class CovarianceEstimate:
    """Covariance of the free, interior parameters (physical units) or None with a note."""

    names: list[str]
    matrix: np.ndarray | None
    stderr: dict[str, float]
    ci: dict[str, tuple[float, float]]
    note: str | None
    condition: float | None = None   # of the column-equilibrated information matrix
    null_directions: list[str] = field(default_factory=list)   # every (near-)null combination
    classical: np.ndarray | None = None     # σ²(JᵀJ)⁻¹ (sandwich per output) when `matrix` is HAC
    classical_stderr: dict[str, float] = field(default_factory=dict)
    robust_bandwidth: float | None = None   # set when `matrix` is the HAC covariance


def null_directions(eigval: np.ndarray, eigvec: np.ndarray, labels: list[str],
                    limit: float = CONDITION_LIMIT) -> list[str]:
    """Every eigen-direction whose eigenvalue is below λmax/limit, as a named combination.

    Parameters
    ----------
    eigval : numpy.ndarray
        Eigenvalues of the (equilibrated) information matrix in ascending order, shape (n,).
    eigvec : numpy.ndarray
        The matching eigenvectors as columns, shape (n, n).
    labels : list of str
        Name of each variable (row of `eigvec`).
    limit : float, optional
        Condition limit: a direction is null when its eigenvalue is at most λmax / `limit`.

    Returns
    -------
    list of str
        One combination per null direction, as `combination` writes it.
    """
    top = max(float(eigval[-1]), 1e-300)
    return [combination(eigvec[:, k], labels) for k in range(eigval.size) if eigval[k] <= top / limit]


def combination(vector: np.ndarray, labels: list[str]) -> str:
    """A direction written as its largest terms, e.g. ``+0.71*k -0.70*c``.

    Parameters
    ----------
    vector : numpy.ndarray
        Direction in the variables, shape (n,).
    labels : list of str
        Name of each variable.

    Returns
    -------
    str
        Up to six terms with |coefficient| > 0.1, largest first; the name of the largest entry alone
        when none exceeds 0.1.
    """
    order = np.argsort(-np.abs(vector))
    terms = [f"{vector[i]:+.2f}*{labels[i]}" for i in order if abs(vector[i]) > 0.1][:6]
    return " ".join(terms) if terms else labels[int(order[0])]


def estimate_covariance(jac: np.ndarray, residual: np.ndarray, labels: list[str], values: np.ndarray,
                        scale: np.ndarray, keep: np.ndarray, n_params: int,
                        level: float = 0.95, groups: np.ndarray | None = None,
                        sample_keys: np.ndarray | None = None, experiment_keys: np.ndarray | None = None,
                        robust: bool = False) -> CovarianceEstimate:
    """Covariance from the residual Jacobian in scaled variables.

    Parameters
    ----------
    jac : numpy.ndarray
        (ndata, ncols) Jacobian of the weighted residual w.r.t. the scaled decision variables;
        the first `n_params` columns are parameters, the rest nuisance variables (initial states).
    residual : numpy.ndarray
        Weighted residual at the solution, shape (ndata,).
    labels : list of str
        Name of each column.
    values : numpy.ndarray
        Value of each column in physical units, shape (ncols,).
    scale : numpy.ndarray
        Scale of each column, physical = scale * scaled, shape (ncols,).
    keep : numpy.ndarray
        Boolean mask of the columns to include (parameters on an active bound are left out, reported
        as such).
    n_params : int
        Number of leading columns that are parameters.
    level : float, optional
        Confidence level of the intervals (Student-t with ndata − nfree degrees of freedom).
    groups : numpy.ndarray or None, optional
        The output (or equation) of each residual row, a non-negative integer. Each group gets
        its own noise variance s_g² = r_gᵀr_g / (n_g (1 - p/n)) and the covariance is the sandwich
        (JᵀJ)⁻¹ JᵀSJ (JᵀJ)⁻¹, S = diag(s_g²): the fit's weights (1/std of each output by default) need
        not match the noise levels. With one group this is the usual σ²(JᵀJ)⁻¹.
    sample_keys, experiment_keys : numpy.ndarray or None, optional
        Per row, the sample (increasing in time) and the experiment it belongs to; used with `robust`.
    robust : bool, optional
        With `robust` (and both keys given), the reported matrix is the HAC (Newey-West) covariance of
        `solvers/inference/robust_covariance.py`, the classical one kept beside it.

    Returns
    -------
    CovarianceEstimate
        Covariance, standard errors and confidence intervals of the kept parameters in physical units,
        with the condition number of the equilibrated information matrix. Where no covariance can be
        given (non-finite Jacobian, no free variable, no degree of freedom, overflow, a (near-)singular
        information matrix, a degenerate result) `matrix` is None and `note` says why; a singular
        matrix also lists its `null_directions`.
    """
    cols = np.flatnonzero(keep)
    j = jac[:, cols]
    ndata, nvar = j.shape
    dof = ndata - nvar
    names = [labels[c] for c in cols if c < n_params]
    if not (np.all(np.isfinite(j)) and np.all(np.isfinite(residual))):
        return CovarianceEstimate(names, None, {}, {}, "the residual or its Jacobian is not finite at the "
                                  "solution (the simulation diverged); no covariance")
    if nvar == 0:
        return CovarianceEstimate(names, None, {}, {}, "every free variable is on a bound; no covariance "
                                  "(widen the bounds to get standard errors)")
    if dof <= 0:
        return CovarianceEstimate(names, None, {}, {}, f"{ndata} residuals for {nvar} free variables: "
                                  "no degree of freedom left to estimate the noise")
    with np.errstate(over="ignore", invalid="ignore"):   # an overflow is reported below, not warned
        info = j.T @ j
    if not np.all(np.isfinite(info)):
        return CovarianceEstimate(names, None, {}, {}, "the information matrix overflows (weighted residual "
                                  "Jacobian too large); rescale the data or the output weights")
    d = np.sqrt(np.maximum(np.diag(info), 1e-300))
    normed = info / np.outer(d, d)   # column-equilibrated, so the test does not depend on units
    eigval, eigvec = np.linalg.eigh(normed)
    condition = float(eigval[-1] / max(eigval[0], 1e-300))
    lab = [labels[c] for c in cols]
    if eigval[0] <= eigval[-1] / CONDITION_LIMIT:
        kind = "indefinite" if eigval[0] < 0 else "singular"
        nulls = null_directions(eigval, eigvec, lab)
        return CovarianceEstimate(
            names, None, {}, {},
            f"information matrix is {kind} (condition {condition:.1e}); "
            f"not identifiable from these data: {'; '.join(nulls)}", condition, nulls)
    inv = np.linalg.inv(normed) / np.outer(d, d)
    counts = None if groups is None else np.bincount(groups)
    if groups is not None and counts is not None and np.count_nonzero(counts) > 1:
        group_var = np.bincount(groups, weights=residual * residual) / np.maximum(counts * dof / ndata, 1e-300)
        meat = j.T @ (j * group_var[groups][:, None])
        cov_scaled = inv @ meat @ inv
    else:
        cov_scaled = float(residual @ residual) / dof * inv
    sc = scale[cols]
    npar = len(names)
    cov = (cov_scaled * np.outer(sc, sc))[:npar, :npar]
    if not (np.all(np.isfinite(cov)) and np.all(np.diag(cov) > 0)):
        return CovarianceEstimate(names, None, {}, {}, "the covariance is numerically degenerate (a zero "
                                  "or non-finite variance; the weights or scales differ by too many "
                                  "orders of magnitude)", condition)
    stderr, ci = _intervals(cov, cols[:npar], labels, values, level, dof)
    if not robust or sample_keys is None or experiment_keys is None:
        return CovarianceEstimate(names, cov, stderr, ci, None, condition)
    meat, bandwidth = hac_meat(j, residual, sample_keys, experiment_keys)
    hac = (inv @ meat @ inv * (ndata / dof) * np.outer(sc, sc))[:npar, :npar]
    if not (np.all(np.isfinite(hac)) and np.all(np.diag(hac) > 0)):
        return CovarianceEstimate(names, cov, stderr, ci, "the robust covariance is degenerate; the "
                                  "classical one is reported", condition)
    model = noise_model_meat(j, residual, groups, sample_keys, experiment_keys)
    floored = False
    if model is not None:
        floor = noise_model_floor(inv, j, residual, model)[:npar] * (ndata / dof) * sc[:npar] ** 2
        hac, floored = floor_variances(hac, floor)
    r_stderr, r_ci = _intervals(hac, cols[:npar], labels, values, level, dof)
    note = (f"stderr, ci95 and covariance are HAC (Newey-West, Bartlett kernel, bandwidth "
            f"{bandwidth:.1f} samples) because the residual is not white"
            + (", each standard error at least the one under an AR noise model of the residual" if floored else "")
            + "; covariance_classical and stderr_classical are σ²(JᵀJ)⁻¹, valid only for white residuals")
    return CovarianceEstimate(names, hac, r_stderr, r_ci, note, condition, [], cov, stderr, bandwidth)


def noise_model_floor(inv: np.ndarray, jac: np.ndarray, residual: np.ndarray, model: NoiseModelMeat) -> np.ndarray:
    """Variances of the estimates under the AR noise model, each at the residual's size where that
    parameter's sensitivity lies.

    A stationary AR model of the residual has one size for the whole series. Where the residual is
    not stationary in size, that size is wrong for the parameters that live where the residual is
    quiet: on a noise-free fit of a piecewise-constant stiffness whose 3-sample segments miss its
    steps, the three samples at each step hold nearly all of the residual and the stationary model
    spreads their power over every sample; where most segments lie the residual is 15 times (up to
    600 times) smaller than that, and 7 quiet segments got standard errors larger than their values
    (up to 600 times the HAC's) when their estimates were right to 0.2 %. So the AR model's
    variance of parameter i, a_iᵀ Σ a_i (a_i = row i of (JᵀJ)⁻¹Jᵀ), is scaled by
    Σ_t a_it² r_t² / Σ_t a_it² E[r_t²]: the residual's size seen through the parameter's own
    weights over the size the AR model predicts there, E[r rᵀ] = (I − H) Σ (I − H) with H the hat
    matrix, so that the fit's own absorption of coloured noise (strong on a short record, where the
    floor matters) is in both. Under the AR model the ratio is 1 in expectation and the floor is its
    variance, as before; where the residual's size moves, the floor follows it, as the HAC does.

    Parameters
    ----------
    inv : numpy.ndarray
        (JᵀJ)⁻¹, shape (k, k).
    jac : numpy.ndarray
        The Jacobian, shape (n, k).
    residual : numpy.ndarray
        The residual, shape (n,).
    model : NoiseModelMeat
        Jᵀ Σ J, Σ J and Σ's diagonal under the AR noise model (`noise_model_meat`).

    Returns
    -------
    numpy.ndarray
        The floor's variances, shape (k,); 0 where the model predicts (almost) no residual.
    """
    b = jac @ inv   # a_i as columns
    expected = (model.variance - 2 * np.einsum("ti,ti->t", b, model.sigma_jac)
                + np.einsum("ti,ti->t", b @ model.meat, b))
    weights = (b * b).T
    seen, predicted = weights @ (residual * residual), weights @ np.clip(expected, 0.0, None)
    # where the fit absorbs (nearly) all of the noise at a parameter's samples, as when it has as
    # many samples as parameters there, its residual there is rounding and says nothing of the size
    readable = predicted > ABSORBED * (weights @ model.variance)
    size = np.divide(seen, predicted, out=np.zeros_like(seen), where=readable)
    return np.einsum("ij,jk,ki->i", inv, model.meat, inv) * size


def floor_variances(hac: np.ndarray, floor: np.ndarray) -> tuple[np.ndarray, bool]:
    """`hac` with each variance raised to at least `floor`, its correlations kept.

    The prewhitened Bartlett estimator reads the score's colour from a VAR(1) fitted to the score
    itself, which on a short record (121 samples of AR(1) 0.8 noise) is biased towards white and
    leaves intervals that hold the truth in 88 % of fits; the colour of an AR model of the residual
    (`noise_model_floor`) is read from the residual, which is what is coloured. Each standard error
    is the larger of the two (bench/bench_trust.py).

    Parameters
    ----------
    hac : numpy.ndarray
        The HAC covariance, shape (k, k).
    floor : numpy.ndarray
        The least variance of each estimate, shape (k,).

    Returns
    -------
    covariance : numpy.ndarray
        D R D with R the correlation of `hac` and D the larger standard errors.
    raised : bool
        Whether some variance was raised.
    """
    d_hac = np.sqrt(np.diag(hac))
    d_floor = np.sqrt(np.clip(floor, 0.0, None))
    if not (np.all(np.isfinite(d_floor)) and np.all(d_hac > 0)):
        return hac, False
    d = np.maximum(d_hac, d_floor)
    return hac / np.outer(d_hac, d_hac) * np.outer(d, d), bool(np.any(d_floor > d_hac))


def _intervals(cov: np.ndarray, cols, labels, values, level: float, dof: int):
    t = student_t_quantile(0.5 + level / 2, dof)
    stderr, ci = {}, {}
    for k, c in enumerate(cols):
        se = float(np.sqrt(max(cov[k, k], 0.0)))
        stderr[labels[c]] = se
        ci[labels[c]] = (float(values[c] - t * se), float(values[c] + t * se))
    return stderr, ci


def correlation_from(cov: np.ndarray) -> np.ndarray:
    """Correlation matrix of a covariance matrix.

    Parameters
    ----------
    cov : numpy.ndarray
        Covariance matrix with positive diagonal, shape (n, n).

    Returns
    -------
    numpy.ndarray
        cov[i, j] / (sd[i] sd[j]), shape (n, n).
    """
    sd = np.sqrt(np.diag(cov))
    return cov / np.outer(sd, sd)
