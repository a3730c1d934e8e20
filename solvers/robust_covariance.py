"""Covariance robust to correlated residuals: Newey-West (HAC) on the least-squares score.

With residuals r_t that are correlated in time (coloured measurement noise, slow model error),
σ²(JᵀJ)⁻¹ is too small. The estimating equation of least squares is Σ_t s_t = 0 with the score
s_t = J_tᵀ r_t (summed over the outputs measured at sample t). Its long-run covariance

    Ω = Γ_0 + Σ_{l=1..L} w_l (Γ_l + Γ_lᵀ),   Γ_l = Σ_t s_t s_{t-l}ᵀ,   w_l = 1 - l/(L+1) (Bartlett)

gives cov(θ̂) = (JᵀJ)⁻¹ Ω (JᵀJ)⁻¹ (Newey & West 1987). The bandwidth L follows Andrews (1991):
an AR(1) fitted to each score component, L = 1.1447 (α T)^(1/3). Experiments are independent:
lags never cross from one experiment into the next.
"""
from __future__ import annotations

import numpy as np

ANDREWS_BARTLETT = 1.1447
MAX_RHO = 0.97   # an AR(1) coefficient near 1 makes the plug-in bandwidth explode


def scores_by_sample(jac: np.ndarray, residual: np.ndarray, sample_keys: np.ndarray):
    """Score s_t = J_tᵀ r_t summed over the rows that share a sample; keys sorted ascending."""
    keys, inverse = np.unique(sample_keys, return_inverse=True)
    scores = np.zeros((keys.size, jac.shape[1]))
    np.add.at(scores, inverse, jac * residual[:, None])
    return keys, scores


def andrews_bandwidth(blocks: list[np.ndarray]) -> float:
    """Andrews' AR(1) plug-in bandwidth for the Bartlett kernel, pooled over the score components."""
    num = den = 0.0
    total = sum(b.shape[0] for b in blocks)
    for a in range(blocks[0].shape[1]):
        xy = xx = 0.0
        resid_var = []
        for b in blocks:
            s = b[:, a]
            if s.size < 3:
                continue
            xy += float(s[1:] @ s[:-1])
            xx += float(s[:-1] @ s[:-1])
        if xx <= 0:
            continue
        rho = float(np.clip(xy / xx, -MAX_RHO, MAX_RHO))
        for b in blocks:
            s = b[:, a]
            if s.size >= 3:
                resid_var.append(s[1:] - rho * s[:-1])
        sigma2 = float(np.mean(np.concatenate(resid_var) ** 2)) if resid_var else 0.0
        num += 4 * rho ** 2 * sigma2 ** 2 / ((1 - rho) ** 6 * (1 + rho) ** 2)
        den += sigma2 ** 2 / (1 - rho) ** 4
    if den <= 0:
        return 0.0
    alpha = num / den
    return float(min(ANDREWS_BARTLETT * (alpha * total) ** (1 / 3), total / 2))


def hac_meat(jac: np.ndarray, residual: np.ndarray, sample_keys: np.ndarray,
             experiment_keys: np.ndarray) -> tuple[np.ndarray, float]:
    """(Ω, bandwidth L) of the score; `sample_keys` order samples in time, one experiment each.

    Parameters
    ----------
    jac, residual : weighted residual Jacobian (rows × columns) and residual at the solution.
    sample_keys : integer per row, increasing with time inside an experiment; rows sharing a key
        (several outputs at one sample) are one observation of the score.
    experiment_keys : integer per row, the experiment it belongs to.
    """
    keys, scores = scores_by_sample(jac, residual, sample_keys)
    exp_of_key = np.zeros(keys.size, dtype=int)
    exp_of_key[np.searchsorted(keys, sample_keys)] = experiment_keys
    blocks = [scores[exp_of_key == e] for e in np.unique(exp_of_key)]
    bandwidth = andrews_bandwidth(blocks)
    lags = int(np.floor(bandwidth))
    meat = sum(b.T @ b for b in blocks)
    for lag in range(1, lags + 1):
        weight = 1.0 - lag / (lags + 1.0)
        for b in blocks:
            if b.shape[0] > lag:
                gamma = b[lag:].T @ b[:-lag]
                meat = meat + weight * (gamma + gamma.T)
    return meat, bandwidth
