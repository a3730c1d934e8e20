"""Fit metrics and residual analysis (whiteness and independence tests as MATLAB's resid)."""
from __future__ import annotations

import numpy as np

from schemas.fit import ResidualAnalysis, ResidualTest

MAX_LAGS = 25
Z99 = 2.58


def rmse_and_fit(measured: np.ndarray, residual: np.ndarray) -> tuple[float, float]:
    """RMSE and MATLAB `compare` NRMSE fit % over the finite samples."""
    ok = np.isfinite(measured) & np.isfinite(residual)
    if not ok.any():
        return float("nan"), float("nan")
    r, y = residual[ok], measured[ok]
    rmse = float(np.sqrt(np.mean(r ** 2)))
    spread = float(np.linalg.norm(y - y.mean()))
    fit = 100.0 * (1.0 - float(np.linalg.norm(r)) / spread) if spread > 0 else float("nan")
    return rmse, fit


def _xcorr(a: np.ndarray, b: np.ndarray, lags: int) -> np.ndarray:
    """Normalised cross-correlation r_ab(k) = Σ a(t) b(t-k) / (N σa σb), k = -lags..lags.

    Each series is first divided by its largest magnitude (the result does not change): a residual
    of a diverged fit (1e200) would otherwise overflow into NaN correlations.
    """
    a = a / max(float(np.max(np.abs(a), initial=0.0)), 1e-300)
    b = b / max(float(np.max(np.abs(b), initial=0.0)), 1e-300)
    a = a - a.mean()
    b = b - b.mean()
    denom = np.sqrt(np.sum(a * a) * np.sum(b * b))
    if denom == 0:
        return np.zeros(2 * lags + 1)
    n = a.size
    size = 1 << int(np.ceil(np.log2(2 * n)))
    cross = np.fft.irfft(np.fft.rfft(a, size) * np.conj(np.fft.rfft(b, size)), size)  # [k] = Σ a(t+k) b(t)
    ks = np.arange(-lags, lags + 1)
    out = np.where(np.abs(ks) < n, cross[ks % size], 0.0)
    return out / denom


def residual_analysis(output: str, segments: list[tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]],
                      ) -> ResidualAnalysis:
    """Per output; `segments` holds (measured, residual, inputs) per experiment, gaps removed."""
    measured = np.concatenate([s[0] for s in segments])
    resid = np.concatenate([s[1] for s in segments])
    rmse, fit = rmse_and_fit(measured, resid)
    usable = [(m, r, u) for m, r, u in segments if np.isfinite(r).sum() > 2 * MAX_LAGS]
    n_total = sum(int(np.isfinite(r).sum()) for _, r, _ in usable)
    lags = MAX_LAGS if n_total else 0
    bound = Z99 / np.sqrt(max(n_total, 1))
    acf = np.zeros(lags + 1)
    xc: dict[str, np.ndarray] = {}
    for _, r, u in usable:
        ok = np.isfinite(r)
        rr = r[ok]
        weight = rr.size / n_total
        acf += weight * _xcorr(rr, rr, lags)[lags:]
        for name, series in u.items():
            xc[name] = xc.get(name, 0) + weight * _xcorr(rr, series[ok], lags)
    white_max = float(np.max(np.abs(acf[1:]))) if lags else 0.0
    independence = {
        name: ResidualTest(max_abs=float(np.max(np.abs(v))), bound=bound, lags=lags,
                           passed=bool(np.max(np.abs(v)) <= bound))
        for name, v in xc.items()}
    return ResidualAnalysis(
        output=output, rmse=rmse, fit_percent=fit,
        autocorrelation=[float(v) for v in acf],
        whiteness=ResidualTest(max_abs=white_max, bound=bound, lags=lags, passed=white_max <= bound),
        cross_correlation={k: [float(x) for x in v] for k, v in xc.items()},
        independence=independence)
