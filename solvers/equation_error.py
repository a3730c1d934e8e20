"""Equation error: residual ẋ_measured − f(x, u, θ); linear in θ → constrained linear least squares."""
from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from schemas.fit import FitOptions
from solvers.data import ExperimentData
from solvers.derivatives import kernel_averages, smooth_and_differentiate, trapezoid_correction
from solvers.errors import DataError
from solvers.model_compiler import CompiledModel
from solvers.parameters import ParameterLayout
from solvers.problem import LeastSquaresProblem, parameter_constraints, theta_bounds


@dataclass
class EquationData:
    """Per experiment: states X, inputs U, derivatives DX and the rows usable for every equation.

    U is the recorded input, or its average over the derivative's window (see `consistent`).
    """

    x: np.ndarray
    dx: np.ndarray
    rows: np.ndarray
    u: np.ndarray | None = None


def equation_data(cm: CompiledModel, d: ExperimentData, e: int, options: FitOptions,
                  equations: list[int]) -> tuple[EquationData, str | None]:
    """States from direct measurements; derivatives given, or by smoothing differentiation."""
    if cm.model.discrete is not None:   # discrete time: x[k+1] takes the place of dx/dt
        from solvers.discrete import next_state_data
        x, dx = next_state_data(cm, d, e)
        rows = np.flatnonzero(np.isfinite(x).all(axis=0) & np.isfinite(dx[equations]).all(axis=0))
        if rows.size == 0:
            raise DataError("no sample has every state and its next sample present", f"experiments[{e}]")
        return EquationData(x, dx, rows, d.u), "next sample x[k+1] (discrete-time model)"
    state_to_output = {s: o for o, s in cm.direct_outputs.items()}
    x = np.full((cm.nx, d.n), np.nan)
    dx = np.full((cm.nx, d.n), np.nan)
    note = None
    for i, s in enumerate(cm.states):
        if s not in state_to_output:
            raise DataError(
                f"equation error needs every state measured; state '{s}' has no output equal to it. "
                "Use single_shooting or multiple_shooting, or measure the state",
                f"experiments[{e}].outputs")
        raw = d.y[cm.outputs.index(state_to_output[s])]
        if i in d.derivatives:
            x[i], dx[i] = raw, d.derivatives[i]
        elif i in equations:
            x[i], dx[i], note = smooth_and_differentiate(raw, d.t, options.derivative_window,
                                                         options.derivative_order)
        else:
            x[i] = raw
    u = d.u
    if note is not None and not any(i in d.derivatives for i in equations):
        x, u, note = consistent(cm, d, x, options, note)
    rows = np.flatnonzero(np.isfinite(x).all(axis=0) & np.isfinite(dx[equations]).all(axis=0)
                          & np.isfinite(u).all(axis=0))
    if rows.size == 0:
        raise DataError("no sample has every state and derivative present", f"experiments[{e}]")
    return EquationData(x, dx, rows, u), note


def consistent(cm: CompiledModel, d: ExperimentData, x: np.ndarray, options: FitOptions,
               note: str) -> tuple[np.ndarray, np.ndarray, str]:
    """States and inputs averaged with the kernel of the estimated derivative (derivatives.py).

    The estimated derivative is a weighted average of ẋ over its window; the model's right side
    must see the same average of x and u, with u held (zoh) or linear (foh) between samples as
    `input_interpolation` says. Otherwise an input held between samples biases the estimates by
    about half a sample, and any input that changes within the window by more.
    """
    state_to_output = {s: o for o, s in cm.direct_outputs.items()}
    raw = np.vstack([d.y[cm.outputs.index(state_to_output[s])] for s in cm.states])
    w, order = options.derivative_window, options.derivative_order
    held = options.input_interpolation == "zoh"
    xs = kernel_averages(raw, d.t, w, order, held=False)
    if not held:
        derivative = np.vstack([smooth_and_differentiate(r, d.t, w, order)[1] for r in raw])
        xs = trapezoid_correction(xs, derivative, d.t)
    u = kernel_averages(d.u, d.t, w, order, held=held) if cm.nu else d.u
    how = "held (zoh)" if held else "linear (foh)"
    return xs, u, f"{note}; states and inputs ({how}) averaged with the derivative's own kernel"


def _sample_jacobian(cm: CompiledModel, layout: ParameterLayout, equations: list[int],
                     weights: np.ndarray) -> list[ca.Function]:
    """Per experiment: (x, u, t, dx_measured, θ) -> (weighted residual, its Jacobian in θ)."""
    x, u, t = ca.SX.sym("x", cm.nx), ca.SX.sym("u", cm.nu), ca.SX.sym("t")
    dx = ca.SX.sym("dx", len(equations))
    theta = ca.SX.sym("theta", layout.size)
    out = []
    for e in range(len(layout.matrix)):
        p = ca.DM(layout.offset) + ca.DM(layout.matrix[e]) @ theta
        r = (dx - cm.rhs(x, u, p, t)[equations]) * ca.DM(weights[equations])
        out.append(ca.Function("sample_residual", [x, u, t, dx, theta], [r, ca.jacobian(r, theta)]))
    return out


def _affine_in_theta(cm: CompiledModel, layout: ParameterLayout, equations: list[int]) -> bool:
    """Symbolic check (SX) that the used equations are affine in the free parameters."""
    x, u, t = ca.SX.sym("x", cm.nx), ca.SX.sym("u", cm.nu), ca.SX.sym("t")
    theta = ca.SX.sym("theta", layout.size)
    for e in range(len(layout.matrix)):
        p = ca.DM(layout.offset) + ca.DM(layout.matrix[e]) @ theta
        f = cm.rhs(x, u, p, t)[equations]
        if ca.depends_on(ca.jacobian(f, theta), theta):
            return False
    return True


@dataclass
class EquationErrorProblem:
    problem: LeastSquaresProblem
    equations: list[int]
    weights: np.ndarray
    derivative_filter: str | None
    linear: bool
    per_experiment: list[EquationData]


def build_equation_error(cm: CompiledModel, data: list[ExperimentData], layout: ParameterLayout,
                         options: FitOptions) -> EquationErrorProblem:
    deps = cm.equation_parameters()
    free = set(layout.base_names)
    # equations without a free parameter carry no information about θ; they are left out
    equations = [i for i, s in enumerate(cm.states) if deps[s] & free]
    if not equations:
        raise DataError("no state equation depends on a free parameter; nothing to estimate",
                        "model.parameters")
    eqd, notes = [], set()
    for e, d in enumerate(data):
        ed, note = equation_data(cm, d, e, options, equations)
        eqd.append(ed)
        if note:
            notes.add(note)
    weights = np.ones(cm.nx)
    for i in equations:
        values = np.concatenate([ed.dx[i, ed.rows] for ed in eqd])
        sd = float(np.std(values))
        weights[i] = 1.0 / sd if sd > 0 else 1.0

    theta = ca.MX.sym("theta", layout.size)

    def residual() -> ca.MX:
        res = []
        for e, (d, ed) in enumerate(zip(data, eqd)):
            n = ed.rows.size
            p = layout.full(e, theta)
            f = cm.rhs.map(n)(ed.x[:, ed.rows], ed.u[:, ed.rows], ca.repmat(p, 1, n), d.t[ed.rows][None, :])
            r = (ed.dx[equations][:, ed.rows] - f[equations, :]) * weights[equations][:, None]
            res.append(ca.vec(r))
        return ca.vertcat(*res)

    sample_jacobian = _sample_jacobian(cm, layout, equations, weights)
    linear = _affine_in_theta(cm, layout, equations)
    affine: list[tuple[np.ndarray, np.ndarray]] = []

    def jacobian(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(J, r) sample by sample in SX: far cheaper than differentiating the mapped MX graph."""
        if linear and affine:
            jac, r0 = affine[0]
            return jac, jac @ w + r0
        if linear:
            w = np.zeros_like(w)
        blocks, resids = [], []
        for e, (d, ed) in enumerate(zip(data, eqd)):
            n = ed.rows.size
            fe = sample_jacobian[e].map(n)
            rr, jj = fe(ed.x[:, ed.rows], ed.u[:, ed.rows], d.t[ed.rows][None, :],
                        ed.dx[equations][:, ed.rows], w)
            neq = len(equations)
            resids.append(np.array(rr).ravel(order="F"))
            blocks.append(np.array(jj).reshape(neq, n, w.size).transpose(1, 0, 2)
                          .reshape(n * neq, w.size))
        out = np.vstack(blocks), np.concatenate(resids)
        if linear:
            affine.append(out)
        return out
    g, lbg, ubg = parameter_constraints(cm, layout, theta)
    lo, hi = theta_bounds(layout)
    problem = LeastSquaresProblem(
        w=theta, residual_builder=residual, g=ca.vertcat(*g),
        lbg=np.concatenate(lbg) if lbg else np.zeros(0), ubg=np.concatenate(ubg) if ubg else np.zeros(0),
        lbw=lo, ubw=hi, n_theta=layout.size,
        initial_guess=lambda th: th / layout.scale, x0_of=lambda w: [{} for _ in data],
        jacobian=jacobian)
    return EquationErrorProblem(problem, equations, weights, "; ".join(sorted(notes)) or None,
                                linear, eqd)
