"""An autoregressive noise model of a residual, and what it does to least squares.

Output error minimises the plain sum of squares; prediction error with an AR(p) noise model
minimises the sum of squares of the whitened residual A(q) r (generalised least squares). When the
model is right and only the noise is coloured, both are consistent and the second is efficient, so
their difference has covariance V_OE − V_GLS (Hausman, 1978, "Specification tests in
econometrics"); a model error moves the two to different answers, since they weigh the frequencies
differently. Everything here is linear algebra on the fit's own Jacobian and residual: no refit.
"""
from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

MAX_ORDER = 8
IMPULSE_TOLERANCE = 1e-4   # the autocovariance is summed until the impulse response falls below this
MAX_LAGS = 400


def fit_ar(r: np.ndarray, max_order: int = MAX_ORDER) -> tuple[np.ndarray, float]:
    """Yule-Walker AR(p) fit (Levinson-Durbin), p ≤ `max_order` chosen by AIC: A(q) r = e.

    AIC rather than BIC: a small colour that lasts many lags (what a slow missing state leaves) is
    what the tests built on this model must see, and BIC's penalty drops it.

    Parameters
    ----------
    r : numpy.ndarray
        The series, shape (n,).
    max_order : int, optional
        Largest order tried (fewer on short series: at most n/10).

    Returns
    -------
    a : numpy.ndarray
        The polynomial [1, a1, ..., ap], shape (p + 1,); stable (Yule-Walker's always is).
    variance : float
        The innovation variance σ_e².
    """
    n = r.size
    top = min(max_order, n // 10)
    c = np.array([r[:n - k] @ r[k:] for k in range(top + 1)]) / max(n, 1)
    a, e = np.ones(1), float(c[0])
    best = (n * math.log(max(e, 1e-300)), a, e)
    for p in range(1, top + 1):
        if e <= 0:
            break
        k = -(c[p] + a[1:] @ c[p - 1:0:-1]) / e
        a = np.r_[a, 0.0] + k * np.r_[a, 0.0][::-1]
        e *= 1.0 - k * k
        aic = n * math.log(max(e, 1e-300)) + 2 * p
        if aic < best[0]:
            best = (aic, a, e)
    return best[1], best[2]


def whiten(x: np.ndarray, a: np.ndarray) -> np.ndarray:
    """A(q) x along the first axis, the first p rows dropped (they lack their past).

    Parameters
    ----------
    x : numpy.ndarray
        Series along the first axis.
    a : numpy.ndarray
        A(q)'s coefficients, a[0] = 1.

    Returns
    -------
    numpy.ndarray
        The whitened rows.
    """
    p = a.size - 1
    out = x[p:].copy()
    for i in range(1, p + 1):
        out += a[i] * x[p - i:x.shape[0] - i]
    return out


def autocovariance(a: np.ndarray, variance: float) -> np.ndarray:
    """γ(0), γ(1), ... of the AR process A(q) v = e, Var e = `variance`, until it has decayed.

    Parameters
    ----------
    a : numpy.ndarray
        A(q)'s coefficients, a[0] = 1.
    variance : float
        The innovation's variance.

    Returns
    -------
    numpy.ndarray
        γ(0), γ(1), ...
    """
    psi = [1.0]
    while len(psi) < MAX_LAGS:   # impulse response of 1/A(q)
        nxt = -sum(a[i] * psi[-i] for i in range(1, min(a.size, len(psi) + 1)))
        psi.append(nxt)
        if len(psi) > a.size and max(abs(v) for v in psi[-a.size:]) < IMPULSE_TOLERANCE:
            break
    h = np.array(psi)
    return variance * np.array([h[:h.size - k] @ h[k:] for k in range(h.size)])


def coloured_meat(jac: np.ndarray, gamma: np.ndarray) -> np.ndarray:
    """Jᵀ Σ J for stationary noise of autocovariance `gamma` along the rows of `jac`.

    Parameters
    ----------
    jac : numpy.ndarray
        The Jacobian, one row per sample.
    gamma : numpy.ndarray
        The noise's autocovariance γ(0), γ(1), ...

    Returns
    -------
    numpy.ndarray
        Jᵀ Σ J.
    """
    meat = gamma[0] * (jac.T @ jac)
    for k in range(1, min(gamma.size, jac.shape[0])):
        cross = jac[k:].T @ jac[:-k]
        meat += gamma[k] * (cross + cross.T)
    return meat


def chi2_sf(x: float, dof: int) -> float:
    """P(χ²_dof > x) for a whole number of degrees of freedom (closed form).

    Parameters
    ----------
    x : float
        The statistic.
    dof : int
        Degrees of freedom, at least 1.

    Returns
    -------
    float
        The upper tail probability.
    """
    if x <= 0:
        return 1.0
    half = x / 2.0
    if dof % 2 == 0:
        term, total = 1.0, 1.0
        for k in range(1, dof // 2):
            term *= half / k
            total += term
        return min(1.0, math.exp(-half) * total)
    total = math.erfc(math.sqrt(half))
    term = math.sqrt(half) / math.gamma(1.5)
    for k in range(dof // 2):
        total += math.exp(-half) * term
        term *= half / (k + 1.5)
    return min(1.0, total)


def whitened_score_p_value(r: np.ndarray, jac: np.ndarray, groups: np.ndarray, g: np.ndarray) -> float:
    """Score test of adding column(s) `g` to a least-squares fit, under an AR noise model per channel.

    Each channel's rows (in time order) are whitened by the AR(p) model of its residual and scaled by
    its innovation deviation; the whitened residual is then regressed on the whitened candidate with
    the whitened Jacobian projected out (a Lagrange-multiplier test of prediction error at β = 0).
    Under coloured noise this holds its level where a test on the raw residual, even on an effective
    sample size, is liberal: the fit's projection takes low-frequency power out of the residual.

    Parameters
    ----------
    r : numpy.ndarray
        The fit's residual, shape (n,).
    jac : numpy.ndarray
        Its Jacobian, shape (n, k).
    groups : numpy.ndarray
        The channel of each row, shape (n,); rows of a channel in time order.
    g : numpy.ndarray
        Candidate column(s), shape (n,) or (n, m).

    Returns
    -------
    float
        The p-value (χ²(m)); 1 where nothing can be tested.
    """
    g = g.reshape(g.shape[0], -1)
    parts = []
    for c in np.unique(groups):
        rows = np.flatnonzero(groups == c)
        if rows.size < 20:
            continue
        a, variance = fit_ar(r[rows])
        scale = math.sqrt(max(variance, 1e-300))
        parts.append([whiten(x[rows], a) / scale for x in (r, jac, g)])
    if not parts:
        return 1.0
    rw, jw, gw = (np.concatenate([p[i] for p in parts]) for i in range(3))
    basis, s, _ = np.linalg.svd(jw, full_matrices=False) if jw.size else (np.zeros((rw.size, 0)), np.zeros(0), None)
    basis = basis[:, s > (s[0] if s.size else 0.0) * 1e-10]
    r0 = rw - basis @ (basis.T @ rw)
    g0 = gw - basis @ (basis.T @ gw)
    if np.linalg.norm(g0) <= 1e-6 * max(float(np.linalg.norm(gw)), 1e-300) or not r0 @ r0 > 0:
        return 1.0
    coef, *_ = np.linalg.lstsq(g0, r0, rcond=None)
    explained = float((g0 @ coef) @ r0)
    return chi2_sf(explained / (float(r0 @ r0) / r0.size), g.shape[1])


MIN_SERIES = 50   # rows of one (record, channel) series below which no AR model is fitted to it


def toeplitz_times(x: np.ndarray, gamma: np.ndarray) -> np.ndarray:
    """Σ x for stationary noise of autocovariance `gamma` along the rows of `x` (Σ_ts = γ(|t − s|)).

    Parameters
    ----------
    x : numpy.ndarray
        One row per sample, shape (n, k).
    gamma : numpy.ndarray
        The noise's autocovariance γ(0), γ(1), ...

    Returns
    -------
    numpy.ndarray
        Σ x, shape (n, k).
    """
    out = gamma[0] * x
    for k in range(1, min(gamma.size, x.shape[0])):
        out[k:] += gamma[k] * x[:-k]
        out[:-k] += gamma[k] * x[k:]
    return out


class NoiseModelMeat(NamedTuple):
    """Jᵀ Σ J under an AR model of each (record, channel) series of the residual, with the pieces
    the floor of the HAC standard errors reads (`covariance.noise_model_floor`)."""

    meat: np.ndarray        # Jᵀ Σ J, (k, k)
    sigma_jac: np.ndarray   # Σ J, (n, k)
    variance: np.ndarray    # Σ's diagonal: the AR model's γ(0) of each row's series, (n,)


def noise_model_meat(jac: np.ndarray, res: np.ndarray, groups: np.ndarray | None, sample_keys: np.ndarray,
                     experiment_keys: np.ndarray) -> NoiseModelMeat | None:
    """Jᵀ Σ J under an AR(p) model of each (record, channel) series of the residual (`fit_ar`).

    The parametric long-run variance of the score: its colour is read from the residual, the series
    that is coloured, rather than from the score.

    Parameters
    ----------
    jac : numpy.ndarray
        The weighted residual Jacobian, one row per residual, shape (n, k).
    res : numpy.ndarray
        The weighted residual, shape (n,).
    groups : numpy.ndarray or None
        Per row, its channel (None: one channel).
    sample_keys, experiment_keys : numpy.ndarray
        Per row, its sample (increasing in time) and its record.

    Returns
    -------
    NoiseModelMeat or None
        Jᵀ Σ J, Σ J and Σ's diagonal; None where a series is shorter than `MIN_SERIES` rows.
    """
    channel = np.zeros(res.size, dtype=int) if groups is None else groups
    order = np.lexsort((sample_keys, channel, experiment_keys))
    key = experiment_keys[order] * (int(channel.max(initial=0)) + 1) + channel[order]
    sigma_jac = np.zeros(jac.shape)
    variance = np.zeros(res.size)
    for rows in np.split(order, np.flatnonzero(np.diff(key)) + 1):
        if rows.size < MIN_SERIES:
            return None
        a, innovation = fit_ar(res[rows])
        gamma = autocovariance(a, innovation)
        sigma_jac[rows] = toeplitz_times(jac[rows], gamma)
        variance[rows] = gamma[0]
    return NoiseModelMeat(jac.T @ sigma_jac, sigma_jac, variance)
