"""Covariance robust to correlated residuals: Newey-West (HAC) on the least-squares score.

With residuals r_t that are correlated in time (coloured measurement noise, slow model error),
σ²(JᵀJ)⁻¹ is too small. The estimating equation of least squares is Σ_t s_t = 0 with the score
s_t = J_tᵀ r_t (summed over the outputs measured at sample t). Its long-run covariance

    Ω = Γ_0 + Σ_{l=1..L} w_l (Γ_l + Γ_lᵀ),   Γ_l = Σ_t s_t s_{t-l}ᵀ,   w_l = 1 - l/(L+1) (Bartlett)

gives cov(θ̂) = (JᵀJ)⁻¹ Ω (JᵀJ)⁻¹ (Newey & West 1987). The score is prewhitened by a VAR(1) first
and recoloured after (Andrews & Monahan 1992, `prewhiten`); the bandwidth L follows Andrews (1991):
an AR(1) fitted to each (prewhitened) score component, L = 1.1447 (α T)^(1/3). Experiments are
independent: lags never cross from one experiment into the next.
"""
from __future__ import annotations

import numpy as np

ANDREWS_BARTLETT = 1.1447
MAX_RHO = 0.97   # an AR(1) coefficient near 1 makes the plug-in bandwidth explode


def scores_by_sample(jac: np.ndarray, residual: np.ndarray, sample_keys: np.ndarray):
    """Score s_t = J_tᵀ r_t summed over the rows that share a sample; keys sorted ascending.

    Parameters
    ----------
    jac : numpy.ndarray
        Weighted residual Jacobian, shape (rows, columns).
    residual : numpy.ndarray
        Weighted residual, shape (rows,).
    sample_keys : numpy.ndarray
        Integer sample key of each row.

    Returns
    -------
    keys : numpy.ndarray
        The distinct sample keys, ascending, shape (T,).
    scores : numpy.ndarray
        The score of each sample, shape (T, columns).
    """
    products = jac * residual[:, None]
    if sample_keys.size and np.all(sample_keys[1:] >= sample_keys[:-1]):   # rows already in time order
        starts = np.flatnonzero(np.r_[True, sample_keys[1:] != sample_keys[:-1]])
        per = sample_keys.size // starts.size
        if per * starts.size == sample_keys.size and np.all(np.diff(starts) == per):
            # the same number of rows at every sample (every output or equation present):
            # `per` strided additions, far fewer operations than a segmented reduction
            block = products.reshape(starts.size, per, -1)
            scores = block[:, 0].copy()
            for k in range(1, per):
                scores += block[:, k]
            return sample_keys[starts], scores
        return sample_keys[starts], np.add.reduceat(products, starts, axis=0)
    keys, inverse = np.unique(sample_keys, return_inverse=True)
    scores = np.zeros((keys.size, jac.shape[1]))
    np.add.at(scores, inverse, products)
    return keys, scores


def andrews_bandwidth(blocks: list[np.ndarray]) -> float:
    """Andrews' AR(1) plug-in bandwidth for the Bartlett kernel, pooled over the score components.

    Parameters
    ----------
    blocks : list of numpy.ndarray
        The score per experiment, each of shape (T_e, columns); blocks shorter than 3 samples do
        not enter the AR(1) estimate.

    Returns
    -------
    float
        Bandwidth L in samples, at most half the total number of samples; 0 when no block is long
        enough or no component has an AR(1) estimate.
    """
    total = sum(b.shape[0] for b in blocks)
    used = [b for b in blocks if b.shape[0] >= 3]
    if not used:
        return 0.0
    xy = sum(np.einsum("ij,ij->j", b[1:], b[:-1]) for b in used)
    xx = sum(np.einsum("ij,ij->j", b[:-1], b[:-1]) for b in used)
    ok = (xx > 0) & np.isfinite(xx) & np.isfinite(xy)
    if not ok.any():
        return 0.0
    rho = np.clip(np.divide(xy, xx, out=np.zeros_like(xx), where=ok), -MAX_RHO, MAX_RHO)
    sq = sum(np.sum((b[1:] - rho * b[:-1]) ** 2, axis=0) for b in used)
    sigma2 = sq / sum(b.shape[0] - 1 for b in used)
    # α is a ratio of sums of σ⁴: the same for σ² in any common unit, so in that of the largest
    # (the score of a fit stopped far from its optimum reached 1e160, and σ⁴ overflowed into NaN)
    peak = float(np.max(sigma2[ok], initial=0.0))
    if not (np.isfinite(peak) and peak > 0):
        return 0.0
    sigma2 = sigma2 / peak
    num = float(np.sum((4 * rho ** 2 * sigma2 ** 2 / ((1 - rho) ** 6 * (1 + rho) ** 2))[ok]))
    den = float(np.sum((sigma2 ** 2 / (1 - rho) ** 4)[ok]))
    if not (den > 0 and np.isfinite(num)):
        return 0.0
    alpha = num / den
    return float(min(ANDREWS_BARTLETT * (alpha * total) ** (1 / 3), total / 2))


def hac_meat(jac: np.ndarray, residual: np.ndarray, sample_keys: np.ndarray,
             experiment_keys: np.ndarray) -> tuple[np.ndarray, float]:
    """(Ω, bandwidth L) of the score; `sample_keys` order samples in time, one experiment each.

    Parameters
    ----------
    jac : numpy.ndarray
        Weighted residual Jacobian at the solution, shape (rows, columns).
    residual : numpy.ndarray
        Weighted residual at the solution, shape (rows,).
    sample_keys : numpy.ndarray
        Integer per row, increasing with time inside an experiment; rows sharing a key
        (several outputs at one sample) are one observation of the score.
    experiment_keys : numpy.ndarray
        Integer per row, the experiment it belongs to; lags never cross experiments.

    Returns
    -------
    meat : numpy.ndarray
        The long-run covariance Ω of the score, summed over experiments, shape (columns, columns).
    bandwidth : float
        The Andrews bandwidth L in samples (the Bartlett sum uses floor(L) lags).
    """
    keys, scores = scores_by_sample(jac, residual, sample_keys)
    if not experiment_keys.size or np.all(experiment_keys == experiment_keys[0]):   # one experiment
        blocks = [scores]
    else:
        exp_of_key = np.zeros(keys.size, dtype=int)
        exp_of_key[np.searchsorted(keys, sample_keys)] = experiment_keys
        blocks = [scores[exp_of_key == e] for e in np.unique(exp_of_key)]
    whitened, recolour = prewhiten(blocks)
    bandwidth = andrews_bandwidth(whitened)
    lags = int(np.floor(bandwidth))
    meat = np.sum([bartlett_sum(b, lags) for b in whitened], axis=0)
    return recolour @ meat @ recolour.T, bandwidth


def prewhiten(blocks: list[np.ndarray]) -> tuple[list[np.ndarray], np.ndarray]:
    """Andrews & Monahan's prewhitening: a VAR(1) s_t = A s_{t−1} + e_t fitted to the score, the kernel
    estimator run on e_t, and Ω = (I − A)⁻¹ Ω_e (I − A)⁻ᵀ.

    A Bartlett sum on a strongly autocorrelated score is biased low on a few hundred samples (its
    weights shrink exactly the lags that carry the correlation): 95 % intervals of the thermal node
    and the pendulum under AR(1) noise of 0.8 held the truth in 75-85 % of the fits; on the
    prewhitened score the kernel only mops up what the VAR(1) leaves (bench/bench_profile_coverage.py).
    The singular values of A are capped at `MAX_RHO`, as Andrews & Monahan (1992) do, so that
    (I − A)⁻¹ stays bounded; with fewer than ten samples per score component the score is used as it is.

    Parameters
    ----------
    blocks : list of numpy.ndarray
        The score per experiment, each of shape (T_e, columns).

    Returns
    -------
    whitened : list of numpy.ndarray
        e_t per experiment (its first sample dropped), or the blocks themselves.
    recolour : numpy.ndarray
        (I − A)⁻¹, or the identity.
    """
    k = blocks[0].shape[1] if blocks else 0
    used = [b for b in blocks if b.shape[0] >= 3]
    if not used or sum(b.shape[0] - 1 for b in used) < 10 * max(k, 1):
        return blocks, np.eye(k)
    xy = sum(b[1:].T @ b[:-1] for b in used)
    xx = sum(b[:-1].T @ b[:-1] for b in used)
    try:
        a = np.linalg.lstsq(xx, xy.T, rcond=None)[0].T
        u, sv, vt = np.linalg.svd(a)
        a = (u * np.minimum(sv, MAX_RHO)) @ vt
        recolour = np.linalg.inv(np.eye(k) - a)
    except np.linalg.LinAlgError:
        return blocks, np.eye(k)
    if not np.all(np.isfinite(recolour)):
        return blocks, np.eye(k)
    return [b[1:] - b[:-1] @ a.T for b in used], recolour


def bartlett_sum(b: np.ndarray, lags: int) -> np.ndarray:
    """Γ_0 + Σ_{l=1..L} w_l (Γ_l + Γ_lᵀ) = Σ_{t,τ} w(t − τ) s_t s_τᵀ, w(l) = 1 − |l|/(L+1).

    (L+1) w(t − τ) counts the windows of L+1 consecutive samples that hold both t and τ (windows
    that run past either end included), so the sum is CᵀC/(L+1) with C_t the sum of the score over
    window t: two cumulative sums, whatever L (lag by lag costs L products of the whole score
    matrix, and L reaches hundreds for a smooth residual).

    Parameters
    ----------
    b : numpy.ndarray
        The series in time order, shape (T, columns).
    lags : int
        The Bartlett bandwidth L (at most T − 1 is used).

    Returns
    -------
    numpy.ndarray
        The weighted sum of the lag products, shape (columns, columns).
    """
    n = b.shape[0]
    width = min(lags, n - 1) + 1
    cum = np.zeros((n + 1, b.shape[1]))
    np.cumsum(b, axis=0, out=cum[1:])
    first = np.arange(1 - width, n)   # window t covers samples first..first+width-1, clipped
    windows = cum[np.minimum(first + width, n)] - cum[np.maximum(first, 0)]
    return windows.T @ windows / width
