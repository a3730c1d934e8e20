"""Equation residuals of a fitted model, and the scorer that regresses them on candidate terms.

For each state whose values are measured, the equation residual is the Savitzky-Golay derivative of
the smoothed measurement minus the model's right-hand side at the fitted parameters. A candidate
enters as one more regressor next to the linearised free parameters of the equations it touches
(∂f/∂θ). This is the fast screen where states are measured; `scoring_outputs` covers the rest.

The same `TraceData` also describes the fitted trajectory itself (`simulated=True`): every state
from the model's simulation, raw inputs. The effect library computes candidate terms from it.
"""
from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from greyfit.schemas.fit import FitOptions
from greyfit.solvers.data.derivatives import savgol_coefficients, smooth_and_differentiate
from greyfit.solvers.data.experiments import ExperimentData
from greyfit.solvers.dynamics.columns import Columns
from greyfit.solvers.model.compiler import CompiledModel
from greyfit.solvers.screening.scoring import RegressionScorer


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
    jx: list[np.ndarray]         # (n, nx, nx): ∂f/∂x
    p: list[np.ndarray]          # full parameter vector per experiment
    traced: list[int]            # equations a candidate may enter
    free: list[str]              # free parameter names
    measured: set[int]           # states with a direct measurement


def _smooth(series: np.ndarray, t: np.ndarray, options: FitOptions) -> np.ndarray:
    """The smoother the derivatives went through, applied to a series given as it is."""
    smooth, _, _ = smooth_and_differentiate(series, t, options.derivative_window, options.derivative_order)
    return np.where(np.isfinite(smooth), smooth, series)


def _smooth_supplied(derivative: np.ndarray, t: np.ndarray, options: FitOptions) -> np.ndarray:
    """A supplied derivative through the same Savitzky-Golay smoothing as the states beside it."""
    window = options.derivative_window if options.derivative_window % 2 else options.derivative_window + 1
    ok = np.isfinite(derivative)
    dt = np.diff(t)
    if not ok.any() or derivative.size < window or not np.allclose(dt, dt.mean(), rtol=1e-6, atol=0):
        return derivative
    filled = np.interp(t, t[ok], derivative[ok])
    half = window // 2
    out = np.full_like(filled, np.nan)
    out[half:-half] = np.convolve(filled, savgol_coefficients(window, options.derivative_order, 0)[::-1], "valid")
    return np.where(ok, out, np.nan)


def _rhs_jacobians(cm: CompiledModel) -> ca.Function:
    x_sym, u_sym = ca.SX.sym("x", cm.nx), ca.SX.sym("u", cm.nu)
    p_sym, t_sym = ca.SX.sym("p", cm.np), ca.SX.sym("t")
    f = cm.rhs(x_sym, u_sym, p_sym, t_sym)
    # dense: the callers reshape per sample, and a structurally zero block (no input) stays a block
    return ca.Function("greyfit_rhs_jacobians", [x_sym, u_sym, p_sym, t_sym],
                       [f, *(ca.densify(ca.jacobian(f, v)) for v in (p_sym, u_sym, x_sym))])


def rhs_jacobians(cm: CompiledModel, samples: int = 0) -> Columns:
    """(x, u, p, t) -> f, ∂f/∂p, ∂f/∂u, ∂f/∂x on numpy columns, built once per compiled model.

    Every output-error fit's lack-of-fit screen traces its trajectory through these Jacobians:
    building and mapping them anew took a third of that screen on a 101-sample fit.

    Parameters
    ----------
    cm : CompiledModel
        The compiled model (a stand-in model is served uncached and interpreted).
    samples : int, optional
        Samples about to be evaluated (whether compiling pays).

    Returns
    -------
    Columns
        The four outputs, dense, sample k's block in columns k·size2 .. (k+1)·size2 − 1.
    """
    if not isinstance(cm, CompiledModel):
        return Columns(_rhs_jacobians(cm), compile=False)
    return cm.derive(("rhs_jacobians",), lambda: Columns(_rhs_jacobians(cm), 2 * samples))


def build_trace(cm: CompiledModel, data: list[ExperimentData], params: list[np.ndarray],
                simulated: list[np.ndarray], free: list[str], options: FitOptions,
                use_measurements: bool = True) -> TraceData:
    """Equation residuals from the measurements (`use_measurements`), or the bare fitted trajectory.

    Parameters
    ----------
    cm : CompiledModel
        The compiled model.
    data : list of ExperimentData
        The prepared experiments.
    params : list of numpy.ndarray
        (np,) full parameter vector per experiment, at the fit.
    simulated : list of numpy.ndarray
        (nx, n) simulated states per experiment.
    free : list of str
        The free parameters' names.
    options : FitOptions
        The derivative filter's window and order.
    use_measurements : bool
        True: directly measured states are replaced by their smoothed measurements (inputs smoothed
        alike) and their equation residuals formed from the Savitzky-Golay derivative; False: the
        simulated trajectory and raw inputs, residuals NaN, every equation traced.

    Returns
    -------
    TraceData
        States, inputs, residuals (NaN where unknown), Jacobians ∂f/∂p, ∂f/∂u, ∂f/∂x along the
        trajectory, and the traced equations (measured ones that depend on a free parameter).
    """
    sens = rhs_jacobians(cm, sum(d.n for d in data))
    state_of_output = {s: o for o, s in cm.direct_outputs.items()}
    measured = {cm.states.index(s) for s in state_of_output} if use_measurements else set()
    xs, us, res, jps, jus, jxs = [], [], [], [], [], []
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
                dx[i] = _smooth_supplied(d.derivatives[i], d.t, options)
        u = d.u.copy()
        if use_measurements:
            # the inputs go through the same smoother as the states: filtering one side of the
            # equation only leaves a residual that looks like an input delay (seed 004's point)
            for k in range(cm.nu):
                u[k] = _smooth(d.u[k], d.t, options)
        fv, jp, ju, jx = sens(x, u, np.asarray(params[e], dtype=float), d.t[None, :], n=d.n)
        us.append(u)
        xs.append(x)
        res.append(dx - np.array(fv))
        jps.append(np.array(jp).reshape(cm.nx, d.n, cm.np).transpose(1, 0, 2))
        jus.append(np.array(ju).reshape(cm.nx, d.n, cm.nu).transpose(1, 0, 2) if cm.nu else
                   np.zeros((d.n, cm.nx, 0)))
        jxs.append(np.array(jx).reshape(cm.nx, d.n, cm.nx).transpose(1, 0, 2))
    deps = cm.equation_parameters()
    if use_measurements:
        traced = [i for i in sorted(measured) if deps[cm.states[i]] & set(free)]
    else:
        traced = list(range(cm.nx))
    return TraceData(cm, [d.t for d in data], xs, us, res, jps, jus, jxs, params, traced, free, measured)


class EquationScorer(RegressionScorer):
    """Regression of the equation residuals of `equations` on candidate terms."""

    def __init__(self, trace: TraceData, equations: list[int]):
        self.trace, self.equations = trace, equations
        cm = trace.cm
        free_idx = [cm.parameters.index(name) for name in trace.free]
        rows_r, rows_j, labels, self.weights = [], [], [], {}
        for i in equations:
            r_all = np.concatenate([r[i] for r in trace.residual])
            sd = np.nanstd(r_all)
            self.weights[i] = 1.0 / sd if sd > 0 else 1.0
        for e in range(len(trace.t)):
            for i in equations:
                rows_r.append(trace.residual[e][i] * self.weights[i])
                rows_j.append(trace.jp[e][:, i, free_idx] * self.weights[i])
                labels.append(np.full(trace.residual[e][i].size, i))
        r = np.concatenate(rows_r)
        jac = np.vstack(rows_j)
        self.ok = np.isfinite(r) & np.all(np.isfinite(jac), axis=1)
        kept = np.concatenate(labels)[self.ok]
        # one series per equation: their rows follow one another, and a series' autocorrelation is
        # read on its own rows, not across the seam into the next equation's
        self.series = [np.flatnonzero(kept == i) for i in equations] if len(equations) > 1 else None
        super().__init__(r[self.ok], jac[self.ok])

    def parameter_moves(self, delta: np.ndarray) -> dict[str, float]:
        """Changes of the free parameters from a step in the scorer's columns (physical units).

        Parameters
        ----------
        delta : numpy.ndarray
            (n_free,) step in the Jacobian's columns (∂f/∂θ of the free parameters, physical).

        Returns
        -------
        dict of str to float
            Free parameter name -> its change.
        """
        return {name: float(d) for name, d in zip(self.trace.free, delta)}

    def trajectories(self):
        """(states, inputs, times, experiment name) the equation residuals were computed on.

        Returns
        -------
        list of tuple
            Per experiment: states (nx, n), smoothed inputs (nu, n), times (n,), and "" for the name.
        """
        tr = self.trace
        return [(x, u, t, "") for x, u, t in zip(tr.x, tr.u, tr.t)]

    def stack(self, regressor: dict[int, list[np.ndarray]] | None, outputs=None) -> np.ndarray | None:
        """Rows of the candidate's column(s) in the scorer's order; (rows,) or (rows, m).

        Output-path columns (`outputs`) have no equation residual to enter: None.

        Parameters
        ----------
        regressor : dict of int to list of numpy.ndarray or None
            Equation index -> per-experiment column(s), (n,) or (n, m); equations of the scorer it
            does not name get zeros.
        outputs : dict or None
            Output-path columns; when given the result is None.

        Returns
        -------
        numpy.ndarray or None
            The weighted rows at the scorer's finite residuals; None without an equation regressor.
        """
        if outputs or not regressor:
            return None
        parts = []
        width = None
        for cols in regressor.values():
            width = None if np.ndim(cols[0]) == 1 else cols[0].shape[1]
        for e in range(len(self.trace.t)):
            n = self.trace.t[e].size
            for i in self.equations:
                if i in regressor:
                    parts.append(regressor[i][e] * self.weights[i])
                else:
                    parts.append(np.zeros(n) if width is None else np.zeros((n, width)))
        return np.concatenate(parts)[self.ok]
