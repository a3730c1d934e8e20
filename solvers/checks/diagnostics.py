"""Fit metrics and residual analysis (whiteness and independence tests, MATLAB `resid` style).

Both tests look at the largest |correlation| over many lags. A per-lag 99 % band (2.58/√N, what
`resid` draws) tested at 25 lags at once rejects a white residual about 21 % of the time, so the band
here is Šidák-corrected for the number of lags looked at: the residual passes when every lag is
inside it, and a white residual fails with probability `LEVEL` (family-wise; at most `LEVEL` where
the lags are correlated, as the cross-correlations with a slowly varying input are).
"""
from __future__ import annotations

import functools
import math
from statistics import NormalDist

import numpy as np

from greyfit.schemas.fit import ResidualAnalysis, ResidualTest

MAX_LAGS = 25
LEVEL = 0.01   # family-wise false-alarm rate of each test on a white residual


def rmse_and_fit(measured: np.ndarray, residual: np.ndarray) -> tuple[float, float]:
    """RMSE and MATLAB `compare` NRMSE fit % over the finite samples.

    Parameters
    ----------
    measured : numpy.ndarray
        Measured output, shape (N,).
    residual : numpy.ndarray
        Residual (simulated − measured or the reverse; only its size matters), shape (N,).

    Returns
    -------
    rmse : float
        Root mean square of the residual; NaN without a finite sample.
    fit : float
        100 (1 − ‖r‖ / ‖y − ȳ‖) in percent; NaN for a constant measurement or no finite sample.
    """
    ok = np.isfinite(measured) & np.isfinite(residual)
    if not ok.all():
        measured, residual = measured[ok], residual[ok]
    if not residual.size:
        return float("nan"), float("nan")
    sse = float(residual @ residual)
    centred = measured - measured.mean()
    spread = math.sqrt(float(centred @ centred))
    fit = 100.0 * (1.0 - math.sqrt(sse) / spread) if spread > 0 else float("nan")
    return math.sqrt(sse / residual.size), fit


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
    size = _fast_length(n + lags)   # no wrap-around within ±lags; a 5-smooth length is fast
    spectra = np.fft.rfft(z, size, axis=1)
    i, j = np.array(pairs, dtype=int).T
    cross = np.fft.irfft(spectra[i] * np.conj(spectra[j]), size, axis=1)   # [k] = Σ a(t+k) b(t)
    ks = np.arange(-lags, lags + 1)
    out = np.where(np.abs(ks) < n, cross[:, ks % size], 0.0)
    denom = np.sqrt(energy[i] * energy[j])
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(denom[:, None] > 0, out / np.where(denom > 0, denom, 1.0)[:, None], 0.0)


@functools.lru_cache(maxsize=64)
def _fast_length(n: int) -> int:
    """The smallest 2^a 3^b 5^c ≥ n."""
    best, p5 = 1 << max(n - 1, 0).bit_length(), 1
    while p5 < best:
        p35 = p5
        while p35 < best:
            size = p35 << max(0, (n - 1) // p35).bit_length()   # times the least power of 2 that reaches n
            best = min(best, size)
            p35 *= 3
        p5 *= 5
    return best


@functools.lru_cache(maxsize=256)
def sidak_z(level: float, tested: int) -> float:
    """Per-lag two-sided normal quantile so that `tested` independent lags all pass with 1 - level.

    Šidák's inequality makes it conservative (never above `level`) for correlated lags too.

    Parameters
    ----------
    level : float
        Family-wise false-alarm rate, in (0, 1).
    tested : int
        Number of lags tested at once (at least 1 is used).

    Returns
    -------
    float
        z such that P(|Z| > z) = 1 − (1 − level)^(1/tested).
    """
    per_lag = -math.expm1(math.log1p(-level) / max(tested, 1))   # 1 - (1 - level)^(1/m), no cancellation
    return NormalDist().inv_cdf(1.0 - per_lag / 2.0)


def max_abs_p_value(z: float, tested: int) -> float:
    """Family-wise p-value of max |Z_k| = z over `tested` independent standard normal lags.

    Parameters
    ----------
    z : float
        The largest |correlation| in units of its standard deviation under the null.
    tested : int
        Number of lags.

    Returns
    -------
    float
        1 − (1 − P(|Z| > z))^tested, in [0, 1].
    """
    per_lag = math.erfc(z / math.sqrt(2.0))          # P(|Z| > z), accurate in the far tail
    return float(-math.expm1(tested * math.log1p(-min(per_lag, 1.0))) if per_lag < 1.0 else 1.0)


def max_correlation_test(values: np.ndarray, n: int, lags: int, variance_factor: float = 1.0,
                         level: float = LEVEL) -> ResidualTest:
    """Largest |correlation| of `values` (one per tested lag) against the Šidák band.

    Under the null each value is ≈ N(0, variance_factor/n) (Bartlett); `bound` is the per-lag band,
    so a bar that leaves it in a plot is what fails the test.

    Parameters
    ----------
    values : numpy.ndarray
        Correlation per tested lag, shape (n_lags,).
    n : int
        Number of samples the correlations were computed from.
    lags : int
        Largest lag, reported with the test.
    variance_factor : float, optional
        Variance of √n times a correlation under the null (1 for a white residual; never taken below 1).
    level : float, optional
        Family-wise false-alarm rate.

    Returns
    -------
    ResidualTest
        The largest |value|, the per-lag band, the lags, whether it passed, the p-value and the level;
        a passed test with zero band when nothing was tested or `n` ≤ 0.
    """
    tested = int(values.size)
    return _test(float(np.max(np.abs(values))) if tested else 0.0, variance_factor, n, tested, lags, level)


def _test(max_abs: float, variance_factor: float, n: int, tested: int, lags: int, level: float) -> ResidualTest:
    """`max_correlation_test` of a known largest |correlation| over `tested` lags."""
    if not tested or n <= 0:
        return ResidualTest(max_abs=0.0, bound=0.0, lags=0, passed=True, p_value=1.0, level=level)
    scale = math.sqrt(max(variance_factor, 1.0) / n)
    bound = sidak_z(level, tested) * scale
    return ResidualTest(max_abs=max_abs, bound=bound, lags=lags, passed=bool(max_abs <= bound),
                        p_value=max_abs_p_value(max_abs / scale, tested), level=level)


def _bartlett_factors(acf_residual: np.ndarray, acf_inputs: np.ndarray) -> np.ndarray:
    """Var(√N r_eu(k)) = Σ_j ρ_e(j) ρ_u(j) for e independent of u, one per row of `acf_inputs`;
    1 when e is white.

    A coloured residual and a slowly varying input share long correlations, so their sample
    cross-correlation wanders far more than 1/√N without any dependence (Ljung, System
    Identification, 16.6). The sum is tapered (Bartlett weights) to keep its noise down and never
    made narrower than the white-residual band.
    """
    m = acf_residual.size - 1
    weights = 1.0 - np.arange(1, m + 1) / (m + 1)
    return np.maximum(1.0, 1.0 + 2.0 * (acf_inputs[:, 1:] @ (weights * acf_residual[1:])))


def residual_analysis(output: str, segments: list[tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]],
                      ) -> ResidualAnalysis:
    """Per output; `segments` holds (measured, residual, inputs) per experiment, gaps removed.

    Parameters
    ----------
    output : str
        Name of the output.
    segments : list of tuple
        Per experiment, (measured (N,), residual (N,), inputs by name (N,) each).

    Returns
    -------
    ResidualAnalysis
        As `residual_analyses` for this one output.
    """
    return residual_analyses([output], [segments])[0]


def residual_analyses(outputs: list[str], segments: list[list[tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]]],
                      ) -> list[ResidualAnalysis]:
    """`residual_analysis` of several outputs, `segments[c]` those of output c.

    The outputs of one experiment that see the same samples of the inputs (every output of a
    record without gaps) are correlated in one batched FFT, and each input's autocorrelation is
    computed once for all of them.

    Parameters
    ----------
    outputs : list of str
        Names of the outputs.
    segments : list of list of tuple
        Per output, per experiment: (measured (N,), residual (N,), inputs by name (N,) each).
        Experiments with at most 2·`MAX_LAGS` finite residuals do not enter the correlations.

    Returns
    -------
    list of ResidualAnalysis
        Per output: RMSE and fit %, the residual's autocorrelation and whiteness test, its
        cross-correlation with each input and the independence tests (bands widened by Bartlett's
        factor for a coloured residual); the correlations are averaged over the experiments weighted by
        their samples.
    """
    lags_of = [MAX_LAGS if any(np.isfinite(r).sum() > 2 * MAX_LAGS for _, r, _ in segs) else 0
               for segs in segments]
    acf = [np.zeros(lags + 1) for lags in lags_of]
    xc: list[dict[str, np.ndarray]] = [{} for _ in outputs]
    acf_u: list[dict[str, np.ndarray]] = [{} for _ in outputs]
    n_total = [sum(int(np.isfinite(r).sum()) for _, r, _ in segs if np.isfinite(r).sum() > 2 * MAX_LAGS)
               for segs in segments]
    input_acf: dict[bytes, np.ndarray] = {}
    for s in range(max((len(segs) for segs in segments), default=0)):
        batches: dict[tuple, list[tuple[int, np.ndarray, list[np.ndarray]]]] = {}
        for c, segs in enumerate(segments):
            if s >= len(segs):
                continue
            _, r, u = segs[s]
            ok = np.isfinite(r)
            if ok.sum() <= 2 * MAX_LAGS:
                continue
            series = [u[name][ok] for name in u]
            key = (tuple(u), tuple(x.tobytes() for x in series))
            batches.setdefault(key, []).append((c, r[ok], series))
        for (names, keys), members in batches.items():
            _correlate_batch(members, names, keys, input_acf, acf, xc, acf_u, n_total)
    out = []
    for c, (name, segs) in enumerate(zip(outputs, segments)):
        rmse, fit = rmse_and_fit(np.concatenate([m for m, _, _ in segs]), np.concatenate([r for _, r, _ in segs]))
        lags, n = lags_of[c], n_total[c]
        names = list(xc[c])
        independence = {}
        if names:
            cross = np.vstack([xc[c][u] for u in names])
            factors = _bartlett_factors(acf[c], np.vstack([acf_u[c][u] for u in names]))
            peaks = np.max(np.abs(cross), axis=1)
            independence = {u: _test(float(peaks[k]), float(factors[k]), n, cross.shape[1], lags, LEVEL)
                            for k, u in enumerate(names)}
        out.append(ResidualAnalysis(
            output=name, rmse=rmse, fit_percent=fit, autocorrelation=acf[c].tolist(),
            whiteness=max_correlation_test(acf[c][1:], n, lags),
            cross_correlation={u: xc[c][u].tolist() for u in names},
            independence=independence))
    return out


def _correlate_batch(members, names, keys, input_acf, acf, xc, acf_u, n_total) -> None:
    """Add one experiment's correlations of the outputs in `members` (sharing the input samples
    `keys`) to the running sums, each weighted by its share of the output's samples."""
    n_ch, n_in = len(members), len(names)
    rows = np.vstack([r for _, r, _ in members] + list(members[0][2]))
    missing = [k for k, key in enumerate(keys) if key not in input_acf]
    pairs = ([(i, i) for i in range(n_ch)] + [(i, n_ch + k) for i in range(n_ch) for k in range(n_in)]
             + [(n_ch + k, n_ch + k) for k in missing])
    corr = _correlations(rows, pairs, MAX_LAGS)
    for j, k in enumerate(missing):
        input_acf[keys[k]] = corr[n_ch * (1 + n_in) + j, MAX_LAGS:]
    for i, (c, r, _) in enumerate(members):
        weight = r.size / n_total[c]
        acf[c] += weight * corr[i, MAX_LAGS:]
        for k, name in enumerate(names):
            xc[c][name] = xc[c].get(name, 0) + weight * corr[n_ch + i * n_in + k]
            acf_u[c][name] = acf_u[c].get(name, 0) + weight * input_acf[keys[k]]
