"""Lack of fit of a frequency fit: a systematic gain or phase trend over frequency in the residual.

A fit that misses a pole, a zero or a delay leaves a residual that changes smoothly with frequency;
noise at distinct frequencies (separate sine tests, separate spectral lines) does not. The test asks
whether smooth changes of the fitted response explain more of the residual than noise would:

* each smooth change is a relative perturbation δ(ω) of the fitted response, Ĝ → Ĝ·(1 + δ): a gain
  trend (δ real) or a phase trend (δ imaginary) of degree 0–2 in log ω, and the high-frequency
  shapes of a missing pole, zero or delay (δ = jω/ω_max, (ω/ω_max)²); per data set;
* each enters the fit's residual rows as its first-order change (the cost's weights applied: Ĝδ·w
  for the complex costs, δ itself for the log cost);
* with the fitted parameters' columns projected out, the residual is regressed on them: an F test
  of the explained share against what is left (so the noise level is the residual's own, and the
  test needs no noise estimate); significant at `SIGNIFICANCE` means a structure the model lacks.

Under a right model with independent noise across frequencies the statistic is F(m, n − p − m)
(measured on the benchmark generator, bench/bench_frequency_trust.py: see docs/frequency.md).
"""
from __future__ import annotations

import numpy as np
from scipy import stats

from greyfit.schemas.fit import FitWarning
from greyfit.schemas.frequency import FrequencyResponseResult
from greyfit.solvers.frequency.data import FrequencySet

SIGNIFICANCE = 1e-3     # a right model is flagged in about 0.1 % of fits
MIN_SPARE_ROWS = 10     # rows left after the parameters and the trend columns, else no test
RANK_TOLERANCE = 1e-8   # singular values below this share of the largest are a rank deficit


def trend_perturbations(omega: np.ndarray) -> list[np.ndarray]:
    """The relative perturbations δ(ω) tried: gain and phase trends in log ω, and high-frequency shapes.

    Parameters
    ----------
    omega : numpy.ndarray
        (N,) angular frequencies, increasing.

    Returns
    -------
    list of numpy.ndarray
        Complex (N,) arrays: 1, x, x² (gain) and j, jx, jx² (phase), x = log ω scaled to [−1, 1];
        jω/ω_max and (ω/ω_max)² (a pole, zero or delay just above the band).
    """
    x = np.log(omega)
    span = x[-1] - x[0]
    x = 2 * (x - x[0]) / span - 1 if span > 0 else np.zeros_like(x)
    high = omega / omega[-1]
    gains = [np.ones_like(x), x, x ** 2 - 1.0 / 3.0]
    return [g + 0j for g in gains] + [1j * g for g in gains] + [1j * high, high ** 2 + 0j]


def trend_columns(sets: list[FrequencySet], response: FrequencyResponseResult, weights: list[np.ndarray],
                  cost: str) -> np.ndarray:
    """The residual rows' first-order change under each set's perturbations, block by data set.

    Parameters
    ----------
    sets : list of FrequencySet
        The measured data sets (their frequencies).
    response : FrequencyResponseResult
        The fitted responses per data set, in the same order.
    weights : list of numpy.ndarray
        The cost's per-frequency weights (`problem.data_weights`).
    cost : str
        The fit's cost: "log" has rows (ln|Ĝ/G|, phase); the others weighted complex errors.

    Returns
    -------
    numpy.ndarray
        (Σ 2N_e, Σ m_e) columns, the real rows of a set before its imaginary rows, as the residual.
    """
    rows = sum(2 * s.omega.size for s in sets)
    blocks, at = [], 0
    for s, d, w in zip(sets, response.data, weights):
        g_hat = np.array(d.fitted_real) + 1j * np.array(d.fitted_imag)
        n = s.omega.size
        for delta in trend_perturbations(s.omega):
            z = delta if cost == "log" else g_hat * delta * w
            col = np.zeros(rows)
            col[at:at + n], col[at + n:at + 2 * n] = z.real, z.imag
            blocks.append(col)
        at += 2 * n
    return np.column_stack(blocks) if blocks else np.zeros((rows, 0))


def _orthonormal(a: np.ndarray) -> np.ndarray:
    """An orthonormal basis of a's column space (SVD, rank by `RANK_TOLERANCE`)."""
    if a.size == 0:
        return np.zeros((a.shape[0], 0))
    u, sv, _ = np.linalg.svd(a, full_matrices=False)
    return u[:, sv > RANK_TOLERANCE * max(float(sv[0]), 1e-300)] if sv.size else u[:, :0]


def trend_test(residual: np.ndarray, jac: np.ndarray, columns: np.ndarray) -> tuple[float, float, int, int] | None:
    """F test of the trend columns on the residual, the parameters' columns projected out.

    Parameters
    ----------
    residual : numpy.ndarray
        (n,) the fit's data residual.
    jac : numpy.ndarray
        (n, p) its Jacobian in the free parameters.
    columns : numpy.ndarray
        (n, m) the trend columns (`trend_columns`).

    Returns
    -------
    tuple of (float, float, int, int) or None
        (p-value, share of the residual explained, trend rank, residual degrees of freedom); None when
        fewer than `MIN_SPARE_ROWS` rows are left or nothing is left to test.
    """
    q = _orthonormal(jac)
    r0 = residual - q @ (q.T @ residual)
    g0 = columns - q @ (q.T @ columns)
    basis = _orthonormal(g0)
    m = basis.shape[1]
    dof = residual.size - q.shape[1] - m
    rss0 = float(r0 @ r0)
    if m == 0 or dof < MIN_SPARE_ROWS or rss0 <= 0:
        return None
    explained = float(np.sum((basis.T @ r0) ** 2))
    rss1 = max(rss0 - explained, 1e-300 * rss0)
    f_stat = (explained / m) / (rss1 / dof)
    return float(stats.f.sf(f_stat, m, dof)), explained / rss0, m, dof


def trend_warnings(sets: list[FrequencySet], response: FrequencyResponseResult, weights: list[np.ndarray],
                   cost: str, residual: np.ndarray, jac: np.ndarray) -> list[FitWarning]:
    """`missing_effect_likely` when the residual holds a systematic gain or phase trend over frequency.

    Parameters
    ----------
    sets : list of FrequencySet
        The measured data sets.
    response : FrequencyResponseResult
        The fitted responses per data set.
    weights : list of numpy.ndarray
        The cost's per-frequency weights (`problem.data_weights`).
    cost : str
        The fit's cost (`options.cost`); "log1p_abs_error" is not a least-squares cost of the errors and
        is not tested.
    residual : numpy.ndarray
        (n,) the fit's data residual.
    jac : numpy.ndarray
        (n, p) its Jacobian in the free parameters not at a bound.

    Returns
    -------
    list of FitWarning
        One warning with the p-value, the share explained and the level when the test is significant;
        else empty.
    """
    if cost == "log1p_abs_error" or residual.size == 0 or not np.all(np.isfinite(residual)):
        return []
    out = trend_test(residual, jac, trend_columns(sets, response, weights, cost))
    if out is None or out[0] >= SIGNIFICANCE:
        return []
    p, share, m, dof = out
    return [FitWarning(
        code="missing_effect_likely",
        message=f"the residual changes systematically with frequency: smooth gain and phase trends explain "
                f"{100 * share:.0f} % of it (F test on {m} trend directions, p = {p:.1g} < {SIGNIFICANCE:g}); "
                "the model misses a pole, a zero or a delay, and its estimates are biased by it: try a "
                "model with one more pole or zero and compare",
        detail={"test": "gain and phase trend over frequency", "p_value": p, "explained": share,
                "directions": m, "dof": dof, "level": SIGNIFICANCE})]
