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
    xs, res, jps, jus = [], [], [], []
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
        fv, jp, ju = sens.map(d.n)(x, d.u, np.repeat(params[e][:, None], d.n, 1), d.t[None, :])
        xs.append(x)
        res.append(dx - np.array(fv))
        jps.append(np.array(jp).reshape(cm.nx, d.n, cm.np).transpose(1, 0, 2))
        jus.append(np.array(ju).reshape(cm.nx, d.n, cm.nu).transpose(1, 0, 2) if cm.nu else
                   np.zeros((d.n, cm.nx, 0)))
    deps = cm.equation_parameters()
    traced = [i for i in sorted(measured) if deps[cm.states[i]] & set(free)]
    return TraceData(cm, [d.t for d in data], xs, [d.u for d in data], res, jps, jus, params, traced,
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
    corr_after: float


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
    total = 0.0
    for k in range(1, min(max_lag, n // 4)):
        rho = float(r[k:] @ r[:-k]) / denom
        if rho < 0.05:
            break
        total += rho
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
        self.n_eff = max(effective_n(self.r0), self.jac.shape[1] + 10.0)

    def stack(self, regressor: dict[int, list[np.ndarray]]) -> np.ndarray:
        parts = []
        for e in range(len(self.trace.t)):
            for i in self.equations:
                if i in regressor:
                    parts.append(regressor[i][e] * self.weights[i])
                else:
                    parts.append(np.zeros(self.trace.t[e].size))
        return np.concatenate(parts)[self.ok]

    def score(self, g: np.ndarray) -> Score | None:
        """g: the stacked candidate column (already restricted to usable rows)."""
        if not np.all(np.isfinite(g)):
            return None
        g0 = g - self.q @ (self.q.T @ g)
        gg = float(g0 @ g0)
        if gg <= 1e-12 * max(float(g @ g), 1e-300):
            return None   # the term is (nearly) a combination of existing ones
        beta = float(g0 @ self.r0) / gg
        resid1 = self.r0 - beta * g0
        rss1 = float(resid1 @ resid1)
        n, p = self.r.size, self.jac.shape[1]
        explained = (self.rss0 - rss1) / self.rss0 if self.rss0 > 0 else 0.0
        dof = max(self.n_eff - p - 1, 1.0)
        f_stat = (self.rss0 - rss1) / max(rss1 / dof, 1e-300)
        p_value = math.erfc(math.sqrt(max(f_stat, 0.0) / 2))   # F(1, large) ≈ χ²(1)
        bic_drop = self.n_eff * math.log(self.rss0 / max(rss1, 1e-300)) - math.log(self.n_eff)
        corr_before = float(np.corrcoef(self.r0, g0)[0, 1]) if np.std(g0) > 0 else 0.0
        corr_after = float(np.corrcoef(resid1, g0)[0, 1]) if np.std(resid1) > 0 else 0.0
        return Score(self.rss0, rss1, n, self.n_eff, explained, f_stat, p_value, bic_drop, beta,
                     corr_before, corr_after)
