"""Jacobian-based covariance σ²(JᵀJ)⁻¹ with bound handling and identifiability notes."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from solvers.statistics import student_t_quantile

CONDITION_LIMIT = 1e12


@dataclass
class CovarianceEstimate:
    """Covariance of the free, interior parameters (physical units) or None with a note."""

    names: list[str]
    matrix: np.ndarray | None
    stderr: dict[str, float]
    ci: dict[str, tuple[float, float]]
    note: str | None


def _combination(vector: np.ndarray, labels: list[str]) -> str:
    order = np.argsort(-np.abs(vector))
    terms = [f"{vector[i]:+.2f}*{labels[i]}" for i in order if abs(vector[i]) > 0.1][:6]
    return " ".join(terms) if terms else labels[int(order[0])]


def estimate_covariance(jac: np.ndarray, residual: np.ndarray, labels: list[str], values: np.ndarray,
                        scale: np.ndarray, keep: np.ndarray, n_params: int,
                        level: float = 0.95, groups: np.ndarray | None = None) -> CovarianceEstimate:
    """Covariance from the residual Jacobian in scaled variables.

    Parameters
    ----------
    jac : (ndata, ncols) Jacobian of the weighted residual w.r.t. the scaled decision variables;
        the first `n_params` columns are parameters, the rest nuisance variables (initial states).
    residual : weighted residual at the solution.
    labels, values, scale : per column; values in physical units, physical = scale * scaled.
    keep : columns to include (parameters on an active bound are left out, reported as such).
    groups : the output (or equation) of each residual row. Each group gets its own noise variance
        s_g² = r_gᵀr_g / (n_g (1 - p/n)) and the covariance is the sandwich (JᵀJ)⁻¹ JᵀSJ (JᵀJ)⁻¹,
        S = diag(s_g²): the fit's weights (1/std of each output by default) need not match the
        noise levels. With one group this is the usual σ²(JᵀJ)⁻¹.
    """
    cols = np.flatnonzero(keep)
    j = jac[:, cols]
    ndata, nvar = j.shape
    dof = ndata - nvar
    names = [labels[c] for c in cols if c < n_params]
    if not (np.all(np.isfinite(j)) and np.all(np.isfinite(residual))):
        return CovarianceEstimate(names, None, {}, {}, "the residual or its Jacobian is not finite at the "
                                  "solution (the simulation diverged); no covariance")
    if dof <= 0:
        return CovarianceEstimate(names, None, {}, {}, f"{ndata} residuals for {nvar} free variables: "
                                  "no degree of freedom left to estimate the noise")
    info = j.T @ j
    d = np.sqrt(np.maximum(np.diag(info), 1e-300))
    normed = info / np.outer(d, d)   # column-equilibrated, so the test does not depend on units
    eigval, eigvec = np.linalg.eigh(normed)
    if eigval[0] <= eigval[-1] / CONDITION_LIMIT:
        lab = [labels[c] for c in cols]
        kind = "indefinite" if eigval[0] < 0 else "singular"
        return CovarianceEstimate(
            names, None, {}, {},
            f"information matrix is {kind} (condition {eigval[-1] / max(eigval[0], 1e-300):.1e}); "
            f"not identifiable from these data: {_combination(eigvec[:, 0], lab)}")
    inv = np.linalg.inv(normed) / np.outer(d, d)
    if groups is not None and np.unique(groups).size > 1:
        row_var = np.empty(ndata)
        for g in np.unique(groups):
            rows = groups == g
            row_var[rows] = float(residual[rows] @ residual[rows]) / (rows.sum() * dof / ndata)
        meat = j.T @ (j * row_var[:, None])
        cov_scaled = inv @ meat @ inv
    else:
        cov_scaled = float(residual @ residual) / dof * inv
    sc = scale[cols]
    cov = cov_scaled * np.outer(sc, sc)
    npar = len(names)
    cov = cov[:npar, :npar]
    t = student_t_quantile(0.5 + level / 2, dof)
    stderr, ci = {}, {}
    for k, c in enumerate(cols[:npar]):
        se = float(np.sqrt(max(cov[k, k], 0.0)))
        stderr[labels[c]] = se
        ci[labels[c]] = (float(values[c] - t * se), float(values[c] + t * se))
    return CovarianceEstimate(names, cov, stderr, ci, None)


def correlation_from(cov: np.ndarray) -> np.ndarray:
    sd = np.sqrt(np.diag(cov))
    return cov / np.outer(sd, sd)
