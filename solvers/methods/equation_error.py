"""Equation error: residual ẋ_measured − f(x, u, θ); linear in θ → constrained linear least squares."""
from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from greyfit.schemas.fit import FitOptions
from greyfit.solvers.data.derivatives import kernel_averages, smooth_and_differentiate, trapezoid_correction
from greyfit.solvers.data.experiments import ExperimentData
from greyfit.solvers.dynamics.columns import Columns
from greyfit.solvers.errors import DataError
from greyfit.solvers.model.compiler import CompiledModel
from greyfit.solvers.model.parameters import ParameterLayout
from greyfit.solvers.nlp.problem import LeastSquaresProblem, parameter_constraints, theta_bounds


@dataclass
class EquationData:
    """Per experiment: states X, inputs U, derivatives DX and the rows usable for every equation.

    U is the recorded input, or its average over the derivative's window (see `consistent`).
    """

    x: np.ndarray
    dx: np.ndarray
    rows: np.ndarray
    u: np.ndarray


def equation_data(cm: CompiledModel, d: ExperimentData, e: int, options: FitOptions,
                  equations: list[int]) -> tuple[EquationData, str | None]:
    """States from direct measurements; derivatives given, or by smoothing differentiation.

    Parameters
    ----------
    cm : CompiledModel
        The compiled model; every state must be measured directly by an output.
    d : ExperimentData
        One experiment's samples (times, inputs, outputs and any given derivatives).
    e : int
        Index of the experiment, used in the field path of errors.
    options : FitOptions
        Derivative window and order, and the input interpolation (zoh or foh).
    equations : list of int
        Indices of the state equations that are fitted; only these need derivatives.

    Returns
    -------
    data : EquationData
        States, derivatives (or next samples in discrete time), inputs and the usable rows.
    note : str or None
        How the derivatives were obtained (smoothing filter, next sample), or None when all were given.

    Raises
    ------
    DataError
        When a state has no output equal to it, or no sample has every state and derivative present.
    """
    if cm.model.discrete is not None:   # discrete time: x[k+1] takes the place of dx/dt
        from greyfit.solvers.model.discrete import next_state_data
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

    Parameters
    ----------
    cm : CompiledModel
        The compiled model; every state is measured directly by an output.
    d : ExperimentData
        One experiment's samples.
    x : numpy.ndarray
        States, shape (nx, n samples); not used: the averages are formed from the raw outputs.
    options : FitOptions
        Derivative window and order, and `input_interpolation` (zoh or foh).
    note : str
        The derivative filter's description, extended in the returned note.

    Returns
    -------
    states : numpy.ndarray
        Kernel-averaged states, shape (nx, n samples).
    inputs : numpy.ndarray
        Kernel-averaged inputs, shape (nu, n samples) (the recorded inputs when the model has none).
    note : str
        `note` with the averaging appended.
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


def _sample_functions(cm: CompiledModel, equations: list[int]) -> ca.Function:
    """(x, u, t, dx_measured, p, weights) -> (weighted residual, its Jacobian in p), per sample.

    Built once per model and set of equations (not per request): θ enters through p = offset + M θ,
    so ∂r/∂θ = ∂r/∂p · M is formed in numpy.
    """
    def build() -> ca.Function:
        x, u, t = ca.SX.sym("x", cm.nx), ca.SX.sym("u", cm.nu), ca.SX.sym("t")
        dx, wts = ca.SX.sym("dx", len(equations)), ca.SX.sym("w", len(equations))
        p = ca.SX.sym("p", cm.np)
        r = (dx - cm.rhs(x, u, p, t)[equations]) * wts
        return ca.Function("ee_residual", [x, u, t, dx, p, wts], [r, ca.jacobian(r, p)])
    return cm.derive(("equation_error_residual", tuple(equations)), build)


def _nonlinear_pairs(cm: CompiledModel, equations: list[int]) -> set[tuple[int, int]]:
    """Parameter pairs (i, j) with ∂²f/∂p_i∂p_j structurally non-zero in the used equations."""
    def build() -> set[tuple[int, int]]:
        x, u, t = ca.SX.sym("x", cm.nx), ca.SX.sym("u", cm.nu), ca.SX.sym("t")
        p = ca.SX.sym("p", cm.np)
        jac = ca.jacobian(cm.rhs(x, u, p, t)[equations], p)
        rows, cols = ca.jacobian(ca.vec(jac), p).sparsity().get_triplet()
        return {(r // len(equations), c) for r, c in zip(rows, cols)}
    return cm.derive(("equation_error_nonlinear_pairs", tuple(equations)), build)


def _affine_in_theta(cm: CompiledModel, layout: ParameterLayout, equations: list[int]) -> bool:
    """The used equations are affine in the free parameters: no pair of parameters that both move
    with θ (in any experiment) has a structurally non-zero second derivative."""
    pairs = _nonlinear_pairs(cm, equations)
    for m in layout.matrix:
        moves = np.any(np.asarray(m) != 0, axis=1)
        if any(moves[i] and moves[j] for i, j in pairs):
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
    sample: Columns | None = None   # the residual and its Jacobian per sample (compiled C or not)


def build_equation_error(cm: CompiledModel, data: list[ExperimentData], layout: ParameterLayout,
                         options: FitOptions) -> EquationErrorProblem:
    """Build the equation-error least-squares problem: residual ẋ_measured − f(x, u, θ), weighted per equation.

    Equations without a free parameter are left out; each used equation is weighted by the inverse
    standard deviation of its measured derivatives. When the equations are affine in θ the Jacobian is
    formed once and reused.

    Parameters
    ----------
    cm : CompiledModel
        The compiled model; every state must be measured directly.
    data : list of ExperimentData
        The experiments.
    layout : ParameterLayout
        The free parameters (θ), their scaling and their mapping to each experiment's parameters.
    options : FitOptions
        Derivative window and order, and input interpolation.

    Returns
    -------
    EquationErrorProblem
        The least-squares problem, the used equations, their weights, the derivative filter note,
        whether it is linear in θ, the per-experiment data and the per-sample residual columns.

    Raises
    ------
    DataError
        When no state equation depends on a free parameter, or from `equation_data`.
    """
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

    samples = sum(ed.rows.size for ed in eqd)
    sample = cm.derive(("equation_error_columns", tuple(equations)),
                       lambda: Columns(_sample_functions(cm, equations), 3 * samples))
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
        neq = len(equations)
        for e, (d, ed) in enumerate(zip(data, eqd)):
            n = ed.rows.size
            p = np.asarray(layout.full(e, w), dtype=float)
            rr, jj = sample(ed.x[:, ed.rows], ed.u[:, ed.rows], d.t[ed.rows][None, :],
                            ed.dx[equations][:, ed.rows], p, weights[equations], n=n)
            resids.append(rr.ravel(order="F"))
            jp = jj.reshape(neq, n, cm.np).transpose(1, 0, 2).reshape(n * neq, cm.np)
            blocks.append(jp @ layout.matrix[e])
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
                                linear, eqd, sample)
