"""Fit metrics and residual analysis (whiteness and independence tests, MATLAB `resid` style).

Both tests look at the largest |correlation| over many lags. A per-lag 99 % band (2.58/√N, what
`resid` draws) tested at 25 lags at once rejects a white residual about 21 % of the time, so the band
here is Šidák-corrected for the number of lags looked at: the residual passes when every lag is
inside it, and a white residual fails with probability `LEVEL` (family-wise; at most `LEVEL` where
the lags are correlated, as the cross-correlations with a slowly varying input are).
"""
from __future__ import annotations

import math
from statistics import NormalDist

import numpy as np

from schemas.fit import ResidualAnalysis, ResidualTest

MAX_LAGS = 25
LEVEL = 0.01   # family-wise false-alarm rate of each test on a white residual


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
    """Normalised cross-correlation r_ab(k) = Σ a(t) b(t-k) / (N σa σb), k = -lags..lags."""
    return _correlations(np.vstack([a, b]), [(0, 1)], lags)[0]


def _correlations(series: np.ndarray, pairs: list[tuple[int, int]], lags: int) -> np.ndarray:
    """`_xcorr` of each (i, j) pair of rows of `series`, from one batched FFT (one row per pair).

    Each series is first divided by its largest magnitude (the result does not change): a residual
    of a diverged fit (1e200) would otherwise overflow into NaN correlations.
    """
    peak = np.max(np.abs(series), axis=1, initial=0.0)
    z = series / np.maximum(peak, 1e-300)[:, None]
    z = z - z.mean(axis=1, keepdims=True)
    energy = np.sum(z * z, axis=1)
    n = z.shape[1]
    size = 1 << int(np.ceil(np.log2(max(2 * n, 1))))
    spectra = np.fft.rfft(z, size, axis=1)
    i, j = np.array(pairs, dtype=int).T
    cross = np.fft.irfft(spectra[i] * np.conj(spectra[j]), size, axis=1)   # [k] = Σ a(t+k) b(t)
    ks = np.arange(-lags, lags + 1)
    out = np.where(np.abs(ks) < n, cross[:, ks % size], 0.0)
    denom = np.sqrt(energy[i] * energy[j])
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(denom[:, None] > 0, out / np.where(denom > 0, denom, 1.0)[:, None], 0.0)


def sidak_z(level: float, tested: int) -> float:
    """Per-lag two-sided normal quantile so that `tested` independent lags all pass with 1 - level.

    Šidák's inequality makes it conservative (never above `level`) for correlated lags too.
    """
    per_lag = -math.expm1(math.log1p(-level) / max(tested, 1))   # 1 - (1 - level)^(1/m), no cancellation
    return NormalDist().inv_cdf(1.0 - per_lag / 2.0)


def max_abs_p_value(z: float, tested: int) -> float:
    """Family-wise p-value of max |Z_k| = z over `tested` independent standard normal lags."""
    per_lag = math.erfc(z / math.sqrt(2.0))          # P(|Z| > z), accurate in the far tail
    return float(-math.expm1(tested * math.log1p(-min(per_lag, 1.0))) if per_lag < 1.0 else 1.0)


def max_correlation_test(values: np.ndarray, n: int, lags: int, variance_factor: float = 1.0,
                         level: float = LEVEL) -> ResidualTest:
    """Largest |correlation| of `values` (one per tested lag) against the Šidák band.

    Under the null each value is ≈ N(0, variance_factor/n) (Bartlett); `bound` is the per-lag band,
    so a bar that leaves it in a plot is what fails the test.
    """
    tested = int(values.size)
    if not tested or n <= 0:
        return ResidualTest(max_abs=0.0, bound=0.0, lags=0, passed=True, p_value=1.0, level=level)
    scale = math.sqrt(max(variance_factor, 1.0) / n)
    max_abs = float(np.max(np.abs(values)))
    bound = sidak_z(level, tested) * scale
    return ResidualTest(max_abs=max_abs, bound=bound, lags=lags, passed=bool(max_abs <= bound),
                        p_value=max_abs_p_value(max_abs / scale, tested), level=level)


def _bartlett_factor(acf_residual: np.ndarray, acf_input: np.ndarray) -> float:
    """Var(√N r_eu(k)) = Σ_j ρ_e(j) ρ_u(j) for e independent of u; 1 when e is white.

    A coloured residual and a slowly varying input share long correlations, so their sample
    cross-correlation wanders far more than 1/√N without any dependence (Ljung, System
    Identification, 16.6). The sum is tapered (Bartlett weights) to keep its noise down and never
    made narrower than the white-residual band.
    """
    m = acf_residual.size - 1
    weights = 1.0 - np.arange(1, m + 1) / (m + 1)
    return max(1.0, 1.0 + 2.0 * float(np.sum(weights * acf_residual[1:] * acf_input[1:])))


def residual_analysis(output: str, segments: list[tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]],
                      ) -> ResidualAnalysis:
    """Per output; `segments` holds (measured, residual, inputs) per experiment, gaps removed."""
    return residual_analyses([output], [segments])[0]


def residual_analyses(outputs: list[str], segments: list[list[tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]]],
                      ) -> list[ResidualAnalysis]:
    """`residual_analysis` of several outputs; an input's autocorrelation is computed once for all
    the outputs that see the same samples of it (every output of a record without gaps)."""
    input_acf: dict[bytes, np.ndarray] = {}
    return [_analysis(name, segs, input_acf) for name, segs in zip(outputs, segments)]


def _analysis(output: str, segments, input_acf: dict[bytes, np.ndarray]) -> ResidualAnalysis:
    measured = np.concatenate([s[0] for s in segments])
    resid = np.concatenate([s[1] for s in segments])
    rmse, fit = rmse_and_fit(measured, resid)
    usable = [(m, r, u) for m, r, u in segments if np.isfinite(r).sum() > 2 * MAX_LAGS]
    n_total = sum(int(np.isfinite(r).sum()) for _, r, _ in usable)
    lags = MAX_LAGS if n_total else 0
    acf = np.zeros(lags + 1)
    xc: dict[str, np.ndarray] = {}
    acf_u: dict[str, np.ndarray] = {}
    for _, r, u in usable:
        ok = np.isfinite(r)
        names = list(u)
        series = [u[name][ok] for name in names]
        keys = [s.tobytes() for s in series]
        missing = [k for k, key in enumerate(keys) if key not in input_acf]
        rows = np.vstack([r[ok], *series])
        pairs = ([(0, 0)] + [(0, k + 1) for k in range(len(names))]
                 + [(k + 1, k + 1) for k in missing])
        corr = _correlations(rows, pairs, lags)
        for j, k in enumerate(missing):
            input_acf[keys[k]] = corr[1 + len(names) + j, lags:]
        weight = rows.shape[1] / n_total
        acf += weight * corr[0, lags:]
        for k, name in enumerate(names):
            xc[name] = xc.get(name, 0) + weight * corr[1 + k]
            acf_u[name] = acf_u.get(name, 0) + weight * input_acf[keys[k]]
    independence = {
        name: max_correlation_test(v, n_total, lags, _bartlett_factor(acf, acf_u[name]))
        for name, v in xc.items()}
    return ResidualAnalysis(
        output=output, rmse=rmse, fit_percent=fit,
        autocorrelation=acf.tolist(),
        whiteness=max_correlation_test(acf[1:], n_total, lags),
        cross_correlation={k: np.asarray(v, dtype=float).tolist() for k, v in xc.items()},
        independence=independence)
