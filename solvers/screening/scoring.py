"""Score-test regression shared by both scorers: a residual r, the linearised existing parameters J,
and candidate columns g. Regressing r on g with J projected out is one Gauss-Newton step of the fit
augmented by the candidate's parameter (a score / Lagrange-multiplier test at β = 0).

The evidence is an F-test on an effective sample size: smoothing (equation residuals) and coloured
noise (output residuals) correlate neighbouring residuals, so n overstates the evidence.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass
class Score:
    rss0: float
    rss1: float
    n: int
    n_eff: float
    explained: float
    f_stat: float
    p_value: float
    bic_drop: float
    beta: float
    corr_before: float


def chi2_sf(x: float, k: int) -> float:
    """Survival function of χ²(k): exact for k = 1, Wilson-Hilferty above.

    Parameters
    ----------
    x : float
        The statistic.
    k : int
        Degrees of freedom, ≥ 1.

    Returns
    -------
    float
        P(χ²(k) > x); 1 for x ≤ 0.
    """
    if x <= 0:
        return 1.0
    if k == 1:
        return math.erfc(math.sqrt(x / 2))
    z = ((x / k) ** (1 / 3) - (1 - 2 / (9 * k))) / math.sqrt(2 / (9 * k))
    return 0.5 * math.erfc(z / math.sqrt(2))


def effective_n(resid: np.ndarray, max_lag: int = 100) -> float:
    """n / (1 + 2 Σ ρ_k) over the lags before the autocorrelation first drops below 0.05, plus the
    geometric tail beyond them (ρ decaying at the rate of its last two lags), which the cut-off
    drops. Measured on complete models under a first-order low-pass noise (bench/bench_discovery_noise.py,
    single unselected candidates, 100 seeds): 5.0-5.6 % / 0.6-1.4 % rejected at nominal 5 % / 1 %
    (6.6-7.0 % / 1.0-1.8 % without the tail). Under AR(1) noise of 0.9 on the mass-spring-damper it
    stays about 2x liberal (10.6 % / 3.2 %): the fit's projection depresses the residual's
    low-frequency power below the noise's. An AR model's spectrum at zero frequency corrects that
    but also reads a real effect's remaining misfit as noise, and lost the EMPS friction; the
    confirming refit's whitened likelihood ratio (`refit_test`) is the gate that holds the loop's
    false positives at the nominal rate.

    Parameters
    ----------
    resid : numpy.ndarray
        (n,) residual series (its mean is removed).
    max_lag : int
        Most lags looked at (also at most n // 4).

    Returns
    -------
    float
        The effective number of independent samples; n itself for a zero residual or n < 8.
    """
    r = resid - resid.mean()
    n = r.size
    denom = float(r @ r)
    if denom == 0 or n < 8:
        return float(n)
    lags = min(max_lag, n // 4)
    acf = _autocovariance(r, lags) / denom
    below = np.flatnonzero(acf < 0.05)
    if not below.size:
        return n / (1 + 2 * float(acf.sum()))
    cut = int(below[0])
    total = float(acf[:cut].sum())
    if cut >= 2 and 0 < acf[cut - 1] < acf[cut - 2]:
        decay = float(acf[cut - 1] / acf[cut - 2])
        total += float(acf[cut - 1]) * decay / (1 - decay)
    return n / (1 + 2 * total)


def _autocovariance(r: np.ndarray, lags: int) -> np.ndarray:
    """Σ_i r_i r_{i+l} for l = 1 … lags − 1 along the last axis, by FFT: zero padding to n + lags
    keeps those lags free of the circular wrap (padding to 2n, as before, doubled the transform of
    every screen's residual columns for lags never read)."""
    n = r.shape[-1]
    size = _fast_length(n + lags)
    spec = np.fft.rfft(r, size, axis=-1)
    return np.fft.irfft(spec * np.conj(spec), size, axis=-1)[..., 1:lags]


def _fast_length(n: int) -> int:
    """The smallest 2^a 3^b 5^c ≥ n (a length the FFT factors well)."""
    best = 1 << max(n - 1, 1).bit_length()
    f5 = 1
    while f5 < best:
        f35 = f5
        while f35 < best:
            f = f35
            while f < n:
                f *= 2
            best = min(best, f)
            f35 *= 3
        f5 *= 5
    return best


def effective_n_of_series(resid: np.ndarray, series: list[np.ndarray] | None) -> np.ndarray:
    """`effective_n` of residual rows that interleave several series (a multi-output record's rows are
    sample-major: y1, y2, y3 at t0, then at t1, ...), column by column.

    Read as one series, the lag-1 autocorrelation of interleaved rows is the correlation between
    outputs, not along time: three outputs of AR(1) 0.8 noise that barely correlate with one another
    read as white, and a candidate that leaves them so scored its BIC drop on n rows where another,
    explaining five times more, scored it on n/50. Each series' variance inflation n_j/n_eff_j is
    weighted by its share of the residual sum of squares: n_eff = n / Σ_j w_j n_j/n_eff_j, the single
    series' value where there is one.

    Parameters
    ----------
    resid : numpy.ndarray
        (n,) or (n, k) residual rows.
    series : list of numpy.ndarray or None
        Row indices of each series; None (or one series): the rows are one series.

    Returns
    -------
    numpy.ndarray
        (k,) effective sample sizes ((1,) for a 1-d `resid`).
    """
    r = resid.reshape(resid.shape[0], -1)
    if series is None or len(series) < 2:
        return effective_n_many(r)
    n = r.shape[0]
    rss = np.einsum("ij,ij->j", r, r)
    inflation = np.zeros(r.shape[1])
    for rows in series:
        part = r[rows]
        rss_j = np.einsum("ij,ij->j", part, part)
        inflation += np.where(rss > 0, rss_j / np.maximum(rss, 1e-300), 1.0 / len(series)) \
            * rows.size / np.maximum(effective_n_many(part), 1.0)
    return n / np.maximum(inflation, 1e-300)


def effective_n_many(resid: np.ndarray, max_lag: int = 100) -> np.ndarray:
    """`effective_n` of every column of `resid` (n, k), the autocorrelations by one FFT.

    Parameters
    ----------
    resid : numpy.ndarray
        (n, k) residual series, one per column.
    max_lag : int
        Most lags looked at (also at most n // 4).

    Returns
    -------
    numpy.ndarray
        (k,) effective sample sizes, as `effective_n` gives them column by column.
    """
    r = resid - resid.mean(axis=0)
    n, k = r.shape
    denom = np.einsum("ij,ij->j", r, r)
    if n < 8:
        return np.full(k, float(n))
    lags = min(max_lag, n // 4)
    acf = _autocovariance(np.ascontiguousarray(r.T), lags).T
    out = np.full(k, float(n))
    for j in range(k):
        if denom[j] == 0:
            continue
        a = acf[:, j] / denom[j]
        below = np.flatnonzero(a < 0.05)
        if not below.size:
            out[j] = n / (1 + 2 * float(a.sum()))
            continue
        cut = int(below[0])
        total = float(a[:cut].sum())
        if cut >= 2 and 0 < a[cut - 1] < a[cut - 2]:
            decay = float(a[cut - 1] / a[cut - 2])
            total += float(a[cut - 1]) * decay / (1 - decay)
        out[j] = n / (1 + 2 * total)
    return out


# a column whose part outside the span of J is below this share of its norm is a combination of the
# existing terms to the accuracy of the sensitivities (computed by another route than J's columns,
# they differ by integration error, some 1e-4): what is left is that error, not an effect, and it can
# correlate with any misfit (a law of an input whose values are ±a, constant in u², scored a BIC drop
# of 1 600 from it). A column this close to J is not identifiable by a refit either.
IN_SPAN = 1e-3


class RegressionScorer:
    """Scores many candidate columns against one residual with one factorisation of J.

    Subclasses provide `stack(regressor)`: the candidate's column(s) in the residual's row order.
    """

    def __init__(self, r: np.ndarray, jac: np.ndarray):
        self.r = r
        self.jac = jac
        keep = np.any(jac != 0, axis=0) if jac.size else np.zeros(0, dtype=bool)
        jac = jac[:, keep]
        if jac.shape[1]:
            # an orthonormal basis of J's range: rank-revealing so unidentifiable columns drop out
            u, s, _ = np.linalg.svd(jac, full_matrices=False)
            self.q = u[:, s > s[0] * 1e-10]
            self.r0 = self.r - self.q @ (self.q.T @ self.r)
        else:
            self.q = np.zeros((self.r.size, 0))
            self.r0 = self.r.copy()
        self.rss0 = float(self.r0 @ self.r0)
        self.n_eff = self._n_eff(self.r0)

    @property
    def n_base(self) -> int:
        """Number of identifiable directions of the existing parameters (the rank of J).

        Returns
        -------
        int
            Columns of the orthonormal basis `q`.
        """
        return self.q.shape[1]

    # row indices of each series the rows interleave (outputs of one record); None: one series
    series: list[np.ndarray] | None = None

    def _n_eff(self, resid: np.ndarray) -> float:
        if self.series is None:
            return max(effective_n(resid), self.n_base + 10.0)
        return max(float(effective_n_of_series(resid, self.series)[0]), self.n_base + 10.0)

    def project(self, g: np.ndarray) -> np.ndarray:
        """Column(s) with the linearised free parameters regressed out.

        Parameters
        ----------
        g : numpy.ndarray
            (rows,) or (rows, m) candidate column(s) in the residual's row order.

        Returns
        -------
        numpy.ndarray
            g − Q Qᵀ g, the same shape.
        """
        return g - self.q @ (self.q.T @ g)

    def stack(self, regressor: dict | None, outputs: dict | None = None) -> np.ndarray | None:
        """The candidate's column(s) in the residual's row order (each scorer has its own rows).

        Parameters
        ----------
        regressor : dict or None
            Equation index -> per-experiment columns of the candidate (`Candidate.equations`).
        outputs : dict or None
            Output index -> per-experiment columns of an output-path candidate (`Candidate.outputs`).

        Returns
        -------
        numpy.ndarray or None
            (rows,) or (rows, m); None where the candidate has no column in this scorer.
        """
        raise NotImplementedError

    def parameter_moves(self, delta: np.ndarray) -> dict[str, float]:
        """Physical changes of the declared parameters from a step in the scorer's columns.

        Parameters
        ----------
        delta : numpy.ndarray
            A step in the coordinates of the scorer's Jacobian columns.

        Returns
        -------
        dict of str to float
            Parameter label -> its change in physical units.
        """
        raise NotImplementedError

    def trajectories(self) -> list[tuple]:
        """(states, inputs, times, experiment name) the residual was computed on, per experiment.

        Returns
        -------
        list of tuple
            Per experiment: states (nx, n), inputs (nu, n), times (n,), the experiment's name.
        """
        raise NotImplementedError

    def score(self, g: np.ndarray | None) -> Score | None:
        """The score test of adding the candidate column(s) g to the fit.

        Parameters
        ----------
        g : numpy.ndarray or None
            The stacked candidate column(s), (rows,) or (rows, m) (`stack`).

        Returns
        -------
        Score or None
            RSS before and after, sample and effective sizes, the share of the residual explained, the F
            statistic and its p-value, the BIC drop, the first coefficient and the correlation with the
            residual; None when g is missing, not finite, (nearly) in the span of J, or there is no residual.
        """
        if g is None or not np.all(np.isfinite(g)):
            return None
        g = g.reshape(g.shape[0], -1)
        g0 = self.project(g)
        if np.linalg.norm(g0) <= IN_SPAN * max(float(np.linalg.norm(g)), 1e-300) or self.rss0 <= 0:
            return None   # the term is (nearly) a combination of existing ones, or nothing to explain
        coef, *_ = np.linalg.lstsq(g0, self.r0, rcond=None)
        fitted = g0 @ coef
        resid1 = self.r0 - fitted
        rss1 = float(resid1 @ resid1)
        m = g.shape[1]
        explained = (self.rss0 - rss1) / self.rss0
        # the effective size comes from what the candidate leaves: a real effect leaves noise,
        # while the residual before it is correlated by the very effect being tested
        n_eff = self._n_eff(resid1)
        dof = max(n_eff - self.n_base - m, 1.0)
        f_stat = (self.rss0 - rss1) / m / max(rss1 / dof, 1e-300)
        p_value = chi2_sf(m * f_stat, m)   # F(m, large) ≈ χ²(m)/m
        bic_drop = n_eff * math.log(self.rss0 / max(rss1, 1e-300)) - m * math.log(n_eff)
        corr_before = float(np.corrcoef(self.r0, fitted)[0, 1]) if np.std(fitted) > 0 else 0.0
        return Score(self.rss0, rss1, self.r.size, n_eff, explained, f_stat, p_value, bic_drop,
                     float(coef[0]), corr_before)

    def score_many(self, columns: list[np.ndarray | None], least_explained: float = 0.0,
                   within: tuple[np.ndarray, np.ndarray] | None = None) -> list[Score | None]:
        """`score` of each entry, the single columns of one length in one vectorised pass.

        The pass projects, regresses and measures the effective size of every single column at once
        (one FFT over all of them): the lack-of-fit check scores a dozen candidates on every fit.
        The numbers are those `score` gives, to rounding.

        Parameters
        ----------
        columns : list of numpy.ndarray or None
            Stacked candidate column(s), as `score` takes them.
        least_explained : float, optional
            A single column that explains a smaller share of the residual is not scored (None): a
            caller that only asks which candidates are significant, where significance needs that
            share (the lack-of-fit check), skips their effective sizes, most of the pass's cost.
        within : tuple of (numpy.ndarray, numpy.ndarray), optional
            (matrix, starts) where each single column ``columns[i]`` is ``matrix[:, starts[i]]``
            (`OutputScorer.stack_matrix`): the columns are then gathered from the matrix row by
            row, where stacking them one strided view at a time took 2 ms of the seat's screen.

        Returns
        -------
        list of Score or None
            One entry per column, as `score` returns.
        """
        out: list[Score | None] = [None] * len(columns)
        single = [i for i, g in enumerate(columns) if g is not None and (g.ndim == 1 or g.shape[1] == 1)
                  and g.shape[0] == self.r.size]
        # stacked first, then checked in one pass (the columns are often strided views)
        if not single:
            g = np.zeros((0, 0))
        elif within is not None:
            g = within[0][:, np.asarray(within[1])[single]]
        else:
            g = np.column_stack([np.asarray(columns[i]).reshape(-1) for i in single])
        finite = np.asarray(np.isfinite(g).all(axis=0), dtype=bool)
        if not finite.all():
            single, g = [i for i, ok in zip(single, finite.tolist()) if ok], g[:, finite]
        vectorised = set(single)
        for i, column in enumerate(columns):
            if i not in vectorised:
                out[i] = self.score(column)
        if not single or self.rss0 <= 0:
            return out
        at = np.asarray(single)
        if least_explained > 0:
            # most candidates explain too little: judged from the Gram numbers, without forming their
            # projected columns (rows × candidates, most of a screen's arithmetic after the
            # propagation); those that may explain enough are scored exactly below, as before
            qg, r0g = self.q.T @ g, g.T @ self.r0
            gg = np.einsum("ij,ij->j", g, g)
            g0g0 = gg - np.einsum("ij,ij->j", qg, qg)
            # cancellation leaves g0g0 a relative error of about eps · gg / g0g0: generous margins
            share = r0g ** 2 / np.maximum(g0g0, 1e-300) / self.rss0
            maybe = (share >= least_explained * (1.0 - 1e-3)) | (g0g0 <= 2 * IN_SPAN ** 2 * gg)
            if not maybe.any():
                return out
            at, g = at[maybe], g[:, maybe]
        g0 = self.project(g)
        norm0, norm = np.linalg.norm(g0, axis=0), np.linalg.norm(g, axis=0)
        live = norm0 > IN_SPAN * np.maximum(norm, 1e-300)
        if not live.any():
            return out
        g0 = g0[:, live]
        coef = (g0.T @ self.r0) / np.einsum("ij,ij->j", g0, g0)
        fitted = g0 * coef
        resid1 = self.r0[:, None] - fitted
        rss1 = np.einsum("ij,ij->j", resid1, resid1)
        enough = (self.rss0 - rss1) / self.rss0 >= least_explained
        if not enough.all():
            live[np.flatnonzero(live)[~enough]] = False
            g0, coef, fitted, resid1, rss1 = g0[:, enough], coef[enough], fitted[:, enough], \
                resid1[:, enough], rss1[enough]
            if not enough.any():
                return out
        n_eff = np.maximum(effective_n_of_series(resid1, self.series), self.n_base + 10.0)
        dof = np.maximum(n_eff - self.n_base - 1, 1.0)
        f_stat = (self.rss0 - rss1) / np.maximum(rss1 / dof, 1e-300)
        bic_drop = n_eff * np.log(self.rss0 / np.maximum(rss1, 1e-300)) - np.log(n_eff)
        centred_r = self.r0 - self.r0.mean()
        centred_f = fitted - fitted.mean(axis=0)
        spread = np.sqrt(np.einsum("ij,ij->j", centred_f, centred_f) * float(centred_r @ centred_r))
        corr = np.divide(centred_r @ centred_f, spread, out=np.zeros_like(spread), where=spread > 0)
        for k, i in enumerate(at[live]):
            out[i] = Score(self.rss0, float(rss1[k]), self.r.size, float(n_eff[k]),
                           float((self.rss0 - rss1[k]) / self.rss0), float(f_stat[k]), chi2_sf(float(f_stat[k]), 1),
                           float(bic_drop[k]), float(coef[k]), float(corr[k]))
        return out

    def forward_select(self, columns: np.ndarray, max_columns: int, alpha: float, min_gain: float) -> list[int]:
        """Greedy forward selection among `columns` (rows × k), e.g. switch times of a parameter.

        A column is added while its partial F-test (against the columns chosen so far) has
        p < alpha and it explains at least `min_gain` more of the residual variance.

        Parameters
        ----------
        columns : numpy.ndarray
            (rows, k) candidate columns in the residual's row order.
        max_columns : int
            Most columns chosen.
        alpha : float
            Significance of each partial test (1: gain alone decides).
        min_gain : float
            Smallest share of the residual sum of squares a new column must explain.

        Returns
        -------
        list of int
            Indices of the chosen columns, in the order chosen.
        """
        c0 = self.project(columns)
        chosen: list[int] = []
        resid = self.r0.copy()
        basis = np.zeros((c0.shape[0], 0))
        for _ in range(max_columns):
            cand = c0 - basis @ (basis.T @ c0) if basis.shape[1] else c0
            norms = np.einsum("ij,ij->j", cand, cand)
            norms[norms <= 1e-12 * max(norms.max(), 1e-300)] = np.inf
            gains = (cand.T @ resid) ** 2 / norms
            if chosen:
                gains[chosen] = -1
            best = int(np.argmax(gains))
            rss = float(resid @ resid)
            new_rss = rss - gains[best]
            unit = cand[:, best] / np.sqrt(norms[best])
            dof = max(self._n_eff(resid - unit * (unit @ resid)) - self.n_base - len(chosen) - 1, 1.0)
            f_stat = gains[best] / max(new_rss / dof, 1e-300)
            if chi2_sf(f_stat, 1) >= alpha or gains[best] < min_gain * self.rss0:
                break
            basis = np.column_stack([basis, unit])
            resid = resid - unit * (unit @ resid)
            chosen.append(best)
        return chosen

    def prune(self, columns: np.ndarray, chosen: list[int], min_gain: float) -> list[int]:
        """Backward elimination: drop the column whose removal costs least while that is < min_gain.

        Parameters
        ----------
        columns : numpy.ndarray
            (rows, k) candidate columns.
        chosen : list of int
            Indices of the columns chosen so far.
        min_gain : float
            Share of the residual sum of squares below which a column's contribution is too small.

        Returns
        -------
        list of int
            The remaining indices, in their order in `chosen`.
        """
        chosen = list(chosen)
        while chosen:
            full = self._rss(columns[:, chosen])
            losses = [self._rss(columns[:, [c for c in chosen if c != k]]) - full for k in chosen]
            worst = int(np.argmin(losses))
            if losses[worst] >= min_gain * self.rss0:
                break
            chosen.pop(worst)
        return chosen

    def _rss(self, g: np.ndarray) -> float:
        if g.shape[1] == 0:
            return self.rss0
        g0 = self.project(g)
        coef, *_ = np.linalg.lstsq(g0, self.r0, rcond=None)
        e = self.r0 - g0 @ coef
        return float(e @ e)
