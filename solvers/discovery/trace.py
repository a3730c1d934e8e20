"""Equation residuals of a fitted model and the regression that scores a candidate term against them.

For each state whose values are measured, the equation residual is the Savitzky-Golay derivative of
the smoothed measurement minus the model's right-hand side at the fitted parameters. A candidate
enters as one more regressor next to the linearised free parameters of the equations it touches
(∂f/∂θ), which is one Gauss-Newton step of an equation-error refit. It is scored by the fraction
of residual variance it explains, an F-test on an effective sample size (SG smoothing and model
error correlate neighbouring residuals, so n overstates the evidence), and the BIC drop.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import casadi as ca
import numpy as np

from schemas.fit import FitOptions
from solvers.data import ExperimentData
from solvers.derivatives import smooth_and_differentiate
from solvers.model_compiler import CompiledModel


@dataclass
class TraceData:
    """Everything a candidate regressor is computed from, per experiment."""

    cm: CompiledModel
    t: list[np.ndarray]
    x: list[np.ndarray]          # (nx, n): smoothed measurements, else simulated states
    u: list[np.ndarray]          # (nu, n)
    residual: list[np.ndarray]   # (nx, n): dx_estimated - f; NaN where unknown
    jp: list[np.ndarray]         # (n, nx, np): ∂f/∂p
    ju: list[np.ndarray]         # (n, nx, nu): ∂f/∂u
    p: list[np.ndarray]          # full parameter vector per experiment
    traced: list[int]            # equations with a residual
    free: list[str]              # free parameter names (shared or per experiment)
    measured: set[int]           # states with a direct measurement


def build_trace(cm: CompiledModel, data: list[ExperimentData], params: list[np.ndarray],
                simulated: list[np.ndarray], free: list[str], options: FitOptions) -> TraceData:
    x_sym, u_sym = ca.SX.sym("x", cm.nx), ca.SX.sym("u", cm.nu)
    p_sym, t_sym = ca.SX.sym("p", cm.np), ca.SX.sym("t")
    f = cm.rhs(x_sym, u_sym, p_sym, t_sym)
    sens = ca.Function("sens", [x_sym, u_sym, p_sym, t_sym],
                       [f, ca.jacobian(f, p_sym), ca.jacobian(f, u_sym)])
    state_of_output = {s: o for o, s in cm.direct_outputs.items()}
    measured = {cm.states.index(s) for s in state_of_output}
    xs, us, res, jps, jus = [], [], [], [], []
    for e, d in enumerate(data):
        x = np.array(simulated[e], dtype=float)
        dx = np.full((cm.nx, d.n), np.nan)
        for i in measured:
            raw = d.y[cm.outputs.index(state_of_output[cm.states[i]])]
            ok = np.isfinite(raw)
            filled = np.interp(d.t, d.t[ok], raw[ok])
            smooth, deriv, _ = smooth_and_differentiate(filled, d.t, options.derivative_window,
                                                        options.derivative_order)
            x[i] = np.where(np.isfinite(smooth), smooth, filled)
            dx[i] = np.where(ok, deriv, np.nan)
            if i in d.derivatives:
                dx[i] = d.derivatives[i]
        # the inputs go through the same smoother as the states: filtering one side of the equation
        # only leaves a residual that looks like an input delay (the point of seed 004's prefilter)
        u = d.u.copy()
        for k in range(cm.nu):
            smooth, _, _ = smooth_and_differentiate(d.u[k], d.t, options.derivative_window,
                                                    options.derivative_order)
            u[k] = np.where(np.isfinite(smooth), smooth, d.u[k])
        fv, jp, ju = sens.map(d.n)(x, u, np.repeat(params[e][:, None], d.n, 1), d.t[None, :])
        us.append(u)
        xs.append(x)
        res.append(dx - np.array(fv))
        jps.append(np.array(jp).reshape(cm.nx, d.n, cm.np).transpose(1, 0, 2))
        jus.append(np.array(ju).reshape(cm.nx, d.n, cm.nu).transpose(1, 0, 2) if cm.nu else
                   np.zeros((d.n, cm.nx, 0)))
    deps = cm.equation_parameters()
    traced = [i for i in sorted(measured) if deps[cm.states[i]] & set(free)]
    return TraceData(cm, [d.t for d in data], xs, us, res, jps, jus, params, traced,
                     free, measured)


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


def _design(trace: TraceData, equations: list[int]):
    """Stacked, weighted residual, base regressors (∂f/∂θ of free parameters) and the row mask."""
    cm = trace.cm
    free_idx = [cm.parameters.index(name) for name in trace.free]
    rows_r, rows_j, weights = [], [], {}
    for i in equations:
        r_all = np.concatenate([r[i] for r in trace.residual])
        sd = np.nanstd(r_all)
        weights[i] = 1.0 / sd if sd > 0 else 1.0
    for e in range(len(trace.t)):
        for i in equations:
            rows_r.append(trace.residual[e][i] * weights[i])
            rows_j.append(trace.jp[e][:, i, free_idx] * weights[i])
    r = np.concatenate(rows_r)
    jac = np.vstack(rows_j)
    ok = np.isfinite(r) & np.all(np.isfinite(jac), axis=1)
    keep = np.any(jac[ok] != 0, axis=0)
    return r, jac[:, keep], ok, weights


def effective_n(resid: np.ndarray, max_lag: int = 100) -> float:
    """n / (1 + 2 Σ ρ_k) over the lags before the autocorrelation first drops below 0.05."""
    r = resid - resid.mean()
    n = r.size
    denom = float(r @ r)
    if denom == 0:
        return float(n)
    lags = min(max_lag, n // 4)
    spec = np.fft.rfft(r, 2 * n)
    acf = np.fft.irfft(spec * np.conj(spec))[1:lags] / denom
    below = np.flatnonzero(acf < 0.05)
    total = float(acf[:below[0]].sum()) if below.size else float(acf.sum())
    return n / (1 + 2 * total)


class EquationScorer:
    """Scores many candidates against the same set of equations with one factorisation."""

    def __init__(self, trace: TraceData, equations: list[int]):
        self.trace, self.equations = trace, equations
        r, jac, ok, self.weights = _design(trace, equations)
        self.ok = ok
        self.r = r[ok]
        self.jac = jac[ok]
        if self.jac.shape[1]:
            q, _ = np.linalg.qr(self.jac)
            self.q = q
            self.r0 = self.r - q @ (q.T @ self.r)
        else:
            self.q = np.zeros((self.r.size, 0))
            self.r0 = self.r
        self.rss0 = float(self.r0 @ self.r0)
        self.n_eff = self._n_eff(self.r0)

    def _n_eff(self, resid: np.ndarray) -> float:
        return max(effective_n(resid), self.jac.shape[1] + 10.0)

    def stack(self, regressor: dict[int, list[np.ndarray]], weighted: bool = True) -> np.ndarray:
        """Rows of the candidate's column(s) in the scorer's order; (rows,) or (rows, m)."""
        parts = []
        width = None
        for cols in regressor.values():
            width = None if np.ndim(cols[0]) == 1 else cols[0].shape[1]
        for e in range(len(self.trace.t)):
            n = self.trace.t[e].size
            for i in self.equations:
                if i in regressor:
                    parts.append(regressor[i][e] * (self.weights[i] if weighted else 1.0))
                else:
                    parts.append(np.zeros(n) if width is None else np.zeros((n, width)))
        return np.concatenate(parts)[self.ok]

    def project(self, g: np.ndarray) -> np.ndarray:
        """Column(s) with the linearised free parameters regressed out."""
        return g - self.q @ (self.q.T @ g)

    def score(self, g: np.ndarray) -> Score | None:
        """g: the stacked candidate column(s), (rows,) or (rows, m), restricted to usable rows."""
        if not np.all(np.isfinite(g)):
            return None
        g = g.reshape(g.shape[0], -1)
        g0 = self.project(g)
        if np.linalg.norm(g0) <= 1e-6 * max(np.linalg.norm(g), 1e-300):
            return None   # the term is (nearly) a combination of existing ones
        coef, *_ = np.linalg.lstsq(g0, self.r0, rcond=None)
        fitted = g0 @ coef
        resid1 = self.r0 - fitted
        rss1 = float(resid1 @ resid1)
        m = g.shape[1]
        n, p = self.r.size, self.jac.shape[1]
        explained = (self.rss0 - rss1) / self.rss0 if self.rss0 > 0 else 0.0
        # the effective size comes from what the candidate leaves: a real effect leaves noise,
        # while the residual before it is correlated by the very effect being tested
        n_eff = self._n_eff(resid1)
        dof = max(n_eff - p - m, 1.0)
        f_stat = (self.rss0 - rss1) / m / max(rss1 / dof, 1e-300)
        p_value = chi2_sf(m * f_stat, m)   # F(m, large) ≈ χ²(m)/m
        bic_drop = n_eff * math.log(self.rss0 / max(rss1, 1e-300)) - m * math.log(n_eff)
        corr_before = float(np.corrcoef(self.r0, fitted)[0, 1]) if np.std(fitted) > 0 else 0.0
        return Score(self.rss0, rss1, n, n_eff, explained, f_stat, p_value, bic_drop, float(coef[0]),
                     corr_before)

    def forward_select(self, columns: np.ndarray, max_columns: int, alpha: float, min_gain: float) -> list[int]:
        """Greedy forward selection among `columns` (rows × k), e.g. step times of a parameter.

        A column is added while its partial F-test (against the columns chosen so far) has
        p < alpha and it explains at least `min_gain` more of the residual variance.
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
            dof = max(self._n_eff(resid - unit * (unit @ resid)) - self.jac.shape[1] - len(chosen) - 1, 1.0)
            f_stat = gains[best] / max(new_rss / dof, 1e-300)
            if chi2_sf(f_stat, 1) >= alpha or gains[best] < min_gain * self.rss0:
                break
            basis = np.column_stack([basis, unit])
            resid = resid - unit * (unit @ resid)
            chosen.append(best)
        return chosen


    def prune(self, columns: np.ndarray, chosen: list[int], min_gain: float) -> list[int]:
        """Backward elimination: drop the column whose removal costs least while that is < min_gain."""
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


def chi2_sf(x: float, k: int) -> float:
    """Survival function of χ²(k): exact for k = 1, Wilson-Hilferty above."""
    if x <= 0:
        return 1.0
    if k == 1:
        return math.erfc(math.sqrt(x / 2))
    z = ((x / k) ** (1 / 3) - (1 - 2 / (9 * k))) / math.sqrt(2 / (9 * k))
    return 0.5 * math.erfc(z / math.sqrt(2))
