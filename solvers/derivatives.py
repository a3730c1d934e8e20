"""Smoothing differentiation of measured states for equation error."""
from __future__ import annotations

import numpy as np


def savgol_coefficients(window: int, order: int, deriv: int) -> np.ndarray:
    """Savitzky-Golay convolution weights for the `deriv`-th derivative at the window centre."""
    half = window // 2
    k = np.arange(-half, half + 1, dtype=float)
    vander = np.vander(k, order + 1, increasing=True)
    pinv = np.linalg.pinv(vander)
    return pinv[deriv] * np.prod(np.arange(1, deriv + 1)) if deriv else pinv[0]


def smooth_and_differentiate(y: np.ndarray, t: np.ndarray, window: int, order: int):
    """(smoothed y, dy/dt, filter description); edges of half a window are NaN (not extrapolated).

    Uniform sampling uses a Savitzky-Golay filter; non-uniform sampling falls back to central
    differences of the raw series, and says so.
    """
    window = window if window % 2 else window + 1
    dt = np.diff(t)
    uniform = np.allclose(dt, dt.mean(), rtol=1e-6, atol=0)
    if not uniform or y.size < window:
        return y.copy(), np.gradient(y, t), "central differences (non-uniform time or short series)"
    half = window // 2
    c0 = savgol_coefficients(window, order, 0)
    c1 = savgol_coefficients(window, order, 1) / dt.mean()
    smooth = np.full_like(y, np.nan)
    deriv = np.full_like(y, np.nan)
    # correlate: reverse the weights for np.convolve
    smooth[half:-half] = np.convolve(y, c0[::-1], mode="valid")
    deriv[half:-half] = np.convolve(y, c1[::-1], mode="valid")
    return smooth, deriv, f"savitzky_golay(window={window}, order={order})"
