"""The confirming refit's likelihood-ratio test, with the measurement noise allowed to be coloured.

BIC counts every sample as independent evidence. Under coloured measurement noise (a sensor's
low-pass, AR(1) drift) a term that fits a slow wander of the noise lowers it by a hundred and more
(measured: a stiffness switching with |v| on AR(1) noise of coefficient 0.9, 500 samples, BIC drop
151 with t = 5.5 on the robust stderr). As in a prediction-error method with a noise model, both
output residuals, before and after the new term, are whitened by the autoregressive model of the
refitted residual (order by BIC, at most 20; order 0 when it is white, and the test is the plain
one), per experiment and output, and the likelihood ratio Σ n log(RSS_before / RSS_after) of the
whitened residuals is tested as χ²(new parameters). A real effect changes the outputs in ways the
noise model does not predict (the switch of a friction, the shape a cubic spring gives a
resonance) and keeps its evidence; a term that rides on the noise's own slow wander loses it.
"""
from __future__ import annotations

import math

import numpy as np

from greyfit.schemas.fit import FitRequest, FitResult
from greyfit.solvers.errors import FitError
from greyfit.solvers.methods.registry import simulates_outputs
from greyfit.solvers.methods.shooting import OutputErrorModel
from greyfit.solvers.screening.scoring import chi2_sf
from greyfit.solvers.screening.screening import fitted_values

AR_MAX_ORDER = 20


def residual_series(req: FitRequest, fit: FitResult) -> list[np.ndarray]:
    """Weighted measured − simulated output, one series per experiment and output (NaN where missing).

    Parameters
    ----------
    req : FitRequest
        The fit's request.
    fit : FitResult
        The fit (estimates and initial states).

    Returns
    -------
    list of numpy.ndarray
        (n_e,) series, experiment-major then output, of the weighted output residual.

    Raises
    ------
    FitError
        When the model or data of the request do not compile or prepare.
    """
    cm, data, layout, theta_s, x0s = fitted_values(req, fit)
    oem = OutputErrorModel(cm, data, layout, req.options)
    out = []
    for e, d in enumerate(data):
        p = np.asarray(layout.full(e, theta_s), dtype=float).ravel()
        x = oem.numeric_trajectory(e, np.array([x0s[e][s] for s in cm.states]), p)
        y = oem.numeric_outputs(e, x, p)
        r = oem.weights[:, None] * (d.y - y)
        out += [np.where(d.mask[j], r[j], np.nan) for j in range(cm.ny)]
    return out


def output_residual(req: FitRequest, fit: FitResult) -> np.ndarray:
    """The same residual at the measured samples in the scorers' row order (sample-major).

    Parameters
    ----------
    req : FitRequest
        The fit's request.
    fit : FitResult
        The fit.

    Returns
    -------
    numpy.ndarray
        (n,) the finite residuals, experiments in order, within one the outputs of each sample together.

    Raises
    ------
    FitError
        When the model or data of the request do not compile or prepare.
    """
    cm, data, *_ = fitted_values(req, fit)
    series = residual_series(req, fit)
    parts, k = [], 0
    for d in data:
        block = np.vstack(series[k:k + cm.ny]).T    # (n, ny)
        parts.append(block[d.mask.T])
        k += cm.ny
    r = np.concatenate(parts)
    return r[np.isfinite(r)]


def ar_coefficients(r: np.ndarray, max_order: int = AR_MAX_ORDER) -> np.ndarray:
    """φ of the AR model of r with the smallest BIC (Yule-Walker by Levinson-Durbin: all orders at once).

    Parameters
    ----------
    r : numpy.ndarray
        (n,) residual series (its mean is removed).
    max_order : int
        Largest order tried.

    Returns
    -------
    numpy.ndarray
        (p,) AR coefficients φ_1..φ_p; empty when order 0 is best (white) or r is constant.
    """
    n = r.size
    x = r - r.mean()
    spec = np.fft.rfft(x, 2 * n)
    acov = np.fft.irfft(spec * np.conj(spec))[:max_order + 1] / n
    c0 = float(acov[0])
    if c0 <= 0:
        return np.zeros(0)
    best_bic, best = n * math.log(c0), np.zeros(0)
    phi, v = np.zeros(0), c0
    for p in range(1, min(max_order, n - 1) + 1):
        k = (acov[p] - phi @ acov[1:p][::-1]) / v
        if not np.isfinite(k) or abs(k) >= 1:
            break
        phi = np.concatenate([phi - k * phi[::-1], [k]])
        v *= 1 - k * k
        bic = n * math.log(v) + p * math.log(n)
        if bic < best_bic:
            best_bic, best = bic, phi.copy()
    return best


def whiten(r: np.ndarray, phi: np.ndarray) -> np.ndarray:
    """e_t = r_t − Σ φ_k r_{t−k}, t ≥ p.

    Parameters
    ----------
    r : numpy.ndarray
        (n,) series.
    phi : numpy.ndarray
        (p,) AR coefficients.

    Returns
    -------
    numpy.ndarray
        (n − p,) the whitened series.
    """
    p = phi.size
    e = r[p:].copy()
    for k in range(1, p + 1):
        e -= phi[k - 1] * r[p - k:r.size - k]
    return e


def refit_likelihood_ratio(old_req: FitRequest, old: FitResult, new_req: FitRequest,
                           new: FitResult) -> tuple[int | None, float | None]:
    """(largest AR order used, p-value) of the refit against the model before; (None, None) for
    equation error or when a residual cannot be simulated.

    Parameters
    ----------
    old_req, old : FitRequest, FitResult
        The model before the new term, and its fit.
    new_req, new : FitRequest, FitResult
        The model with the new term, and its refit.

    Returns
    -------
    tuple of (int or None, float or None)
        The largest AR order the residuals were whitened with, and the p-value of the likelihood ratio
        as χ²(number of new parameters, at least 1).
    """
    if not simulates_outputs(new_req.method):
        return None, None
    try:
        before, after = residual_series(old_req, old), residual_series(new_req, new)
    except (FitError, RuntimeError, ValueError):
        return None, None
    if len(before) != len(after):
        return None, None
    lr, order = 0.0, 0
    for rb, ra in zip(before, after):
        ok = np.isfinite(rb) & np.isfinite(ra)
        rb, ra = rb[ok], ra[ok]
        if ra.size < 20:
            continue
        phi = ar_coefficients(ra, min(AR_MAX_ORDER, ra.size // 10))
        order = max(order, phi.size)
        eb, ea = whiten(rb, phi), whiten(ra, phi)
        rss_b, rss_a = float(eb @ eb), float(ea @ ea)
        if rss_a <= 0 or rss_b <= 0:
            continue
        lr += ea.size * math.log(rss_b / rss_a)
    added = max(new.metrics.nvarys - old.metrics.nvarys, 1)
    return order, chi2_sf(lr, added)
