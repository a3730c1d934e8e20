"""Smoothing differentiation of measured states for equation error."""
from __future__ import annotations

import numpy as np


def savgol_coefficients(window: int, order: int, deriv: int) -> np.ndarray:
    """Savitzky-Golay convolution weights for the `deriv`-th derivative at the window centre.

    Parameters
    ----------
    window : int
        Odd number of samples in the window.
    order : int
        Degree of the local polynomial.
    deriv : int
        Order of the derivative (0: the smoothed value).

    Returns
    -------
    numpy.ndarray
        Weights c_j for the offsets j = −window//2 .. window//2, shape (window,); the derivative
        weights are per unit sample step (divide by Δt for time units).
    """
    half = window // 2
    k = np.arange(-half, half + 1, dtype=float)
    vander = np.vander(k, order + 1, increasing=True)
    pinv = np.linalg.pinv(vander)
    return pinv[deriv] * np.prod(np.arange(1, deriv + 1)) if deriv else pinv[0]


def smooth_and_differentiate(y: np.ndarray, t: np.ndarray, window: int, order: int):
    """(smoothed y, dy/dt, filter description); edges of half a window are NaN (not extrapolated).

    Uniform sampling uses a Savitzky-Golay filter; non-uniform sampling falls back to central
    differences of the raw series, and says so.

    Parameters
    ----------
    y : numpy.ndarray
        Measured series, shape (N,).
    t : numpy.ndarray
        Sample times, shape (N,).
    window : int
        Window length in samples (an even one is raised by one).
    order : int
        Degree of the Savitzky-Golay polynomial.

    Returns
    -------
    smooth : numpy.ndarray
        Smoothed series, shape (N,) (a copy of `y` under central differences).
    deriv : numpy.ndarray
        dy/dt in units of y per time unit, shape (N,).
    description : str
        The filter used, e.g. ``savitzky_golay(window=11, order=3)``.
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


# --- the same averaging on both sides of the equation ------------------------------------------
#
# Any derivative estimate D[x]_k = Σ_j c_j x_{k+j} with Σ c_j = 0 is exactly an average of the
# true derivative over the window: D[x]_k = ∫ K(s) ẋ(s) ds with a piecewise-constant kernel K
# (K = Σ_{m>i} c_m on the interval after sample k+i ≥ k, −Σ_{m≤i} c_m before) and ∫K = 1.
# So ẋ = f(x, u) gives D[x]_k = ⟨K, f(x, u)⟩, and the consistent regressors at sample k are
# ⟨K, x⟩ and ⟨K, u⟩ — not x_k and u_k. The difference matters when u is rough: an input held
# between samples (zoh) makes ẋ jump at every sample, and a centred derivative then mixes the
# intervals on both sides while u_k belongs to the right one only (a bias of about half a sample;
# with an input changing at every sample the pole came out 5x too slow). ⟨K, u⟩ is exact for a
# held (zoh) or linear (foh) input; ⟨K, x⟩ uses the trapezoid on each interval (x is smooth
# inside an interval), leaving a relative error of about (λΔt)²/12 on a mode λ.


def interval_weights(c: np.ndarray) -> np.ndarray:
    """Weights K_i Δt of the 2h intervals of a centred (2h+1)-sample derivative stencil c·Δt.

    Parameters
    ----------
    c : numpy.ndarray
        Derivative stencil per unit sample step, shape (2h+1,), summing to zero.

    Returns
    -------
    numpy.ndarray
        Weight of each interval between consecutive samples of the window, shape (2h,).
    """
    half = c.size // 2
    tail = np.cumsum(c[::-1])[::-1]            # tail[j] = Σ_{m ≥ j} c_m  (index j = offset + half)
    head = np.cumsum(c)                        # head[j] = Σ_{m ≤ j} c_m
    return np.array([tail[i + 1] if i >= half else -head[i] for i in range(2 * half)])


def _held_and_trapezoid(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sample weights for ⟨K, s⟩ of a held signal (interval i takes s_i) and of a linear one."""
    held = np.append(w, 0.0)
    trap = 0.5 * (np.append(w, 0.0) + np.insert(w, 0, 0.0))
    return held, trap


def kernel_averages(signals: np.ndarray, t: np.ndarray, window: int, order: int,
                    held: bool) -> np.ndarray:
    """⟨K, s⟩ at every sample for the kernel K of `smooth_and_differentiate`'s derivative.

    `signals` is (m, N); `held` treats them as constant over each interval (zoh inputs), else as
    linear (trapezoid: foh inputs, states). NaN where the derivative is NaN (half-window edges).

    Parameters
    ----------
    signals : numpy.ndarray
        Signals to average, shape (m, N) (a 1-D series is taken as one row).
    t : numpy.ndarray
        Sample times, shape (N,).
    window : int
        Window length of the derivative in samples (an even one is raised by one).
    order : int
        Degree of the Savitzky-Golay polynomial.
    held : bool
        Constant over each interval if True, linear between samples if False.

    Returns
    -------
    numpy.ndarray
        The averages, shape (m, N). For non-uniform or short records, the averages matching
        `numpy.gradient`'s stencils (no NaN edges).
    """
    signals = np.atleast_2d(np.asarray(signals, dtype=float))
    window = window if window % 2 else window + 1
    dt = np.diff(t)
    uniform = np.allclose(dt, dt.mean(), rtol=1e-6, atol=0)
    out = np.full_like(signals, np.nan)
    if uniform and t.size >= window:
        half = window // 2
        # savgol weights are per sample step: c·Δt sums to 1 over j·Δt
        held_w, trap_w = _held_and_trapezoid(interval_weights(savgol_coefficients(window, order, 1)))
        weights = held_w if held else trap_w
        for r in range(signals.shape[0]):
            out[r, half:-half] = np.convolve(signals[r], weights[::-1], mode="valid")
        return out
    # non-uniform time or a short series: np.gradient's stencils (central inside, one-sided at the
    # ends): interior sample k weighs interval k-1 by h1/(h0+h1) and interval k by h0/(h0+h1)
    if t.size < 2:
        return signals.copy()
    h0, h1 = dt[:-1], dt[1:]
    left, right = h1 / (h0 + h1), h0 / (h0 + h1)
    s = signals
    if held:
        before, after = s[:, :-2], s[:, 1:-1]
        first, last = s[:, 0], s[:, -2]
    else:
        before, after = 0.5 * (s[:, :-2] + s[:, 1:-1]), 0.5 * (s[:, 1:-1] + s[:, 2:])
        first, last = 0.5 * (s[:, 0] + s[:, 1]), 0.5 * (s[:, -2] + s[:, -1])
    out[:, 1:-1] = left * before + right * after
    out[:, 0], out[:, -1] = first, last
    return out


def trapezoid_correction(averages: np.ndarray, derivatives: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Remove the trapezoid's error −Δt²/12·⟨K, ẍ⟩ from ⟨K, x⟩, with ⟨K, ẍ⟩ = d/dt D[x].

    Valid where ẋ is continuous (inputs linear between samples): there a rough input makes ẍ
    large and the plain trapezoid biased (0.4 % on the pole of the issue-#8 test). With held
    inputs ẋ jumps at the samples and D[x] does not estimate ẍ inside the intervals: not used.
    Uniform sampling only (non-uniform records keep the trapezoid).

    Parameters
    ----------
    averages : numpy.ndarray
        Trapezoid averages ⟨K, x⟩, shape (m, N).
    derivatives : numpy.ndarray
        Derivative estimates D[x] of the same signals, shape (m, N).
    t : numpy.ndarray
        Sample times, shape (N,).

    Returns
    -------
    numpy.ndarray
        Corrected averages, shape (m, N), NaN at the first and last sample; `averages` unchanged for
        non-uniform records or fewer than 3 samples.
    """
    dt = np.diff(t)
    if t.size < 3 or not np.allclose(dt, dt.mean(), rtol=1e-6, atol=0):
        return averages
    h = float(dt.mean())
    out = np.full_like(averages, np.nan)
    out[:, 1:-1] = averages[:, 1:-1] - h / 24.0 * (derivatives[:, 2:] - derivatives[:, :-2])
    return out
