"""The design's simulation: outputs and the Fisher information of a model under a given input, as CasADi graphs.

Why a simulation of its own: the fit's kernels take measured inputs as numbers, the design takes
the input as the decision variable. One RK4 step with held inputs (what a DAQ applies) is augmented
with its forward sensitivities S = ∂x/∂θ and run by `mapaccum` over the samples (CasADi's sysid
example's pattern); every sample contributes (∂y/∂θ)ᵀ Σ⁻¹ (∂y/∂θ) to the information matrix.
"""
from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from greyfit.schemas.fit import FitOptions
from greyfit.solvers.dynamics.integration import make_step
from greyfit.solvers.model.compiler import CompiledModel


@dataclass(frozen=True)
class Measured:
    """Which outputs are measured (their rows in the model's output vector) and their noise levels."""

    rows: tuple[int, ...]
    sigma: np.ndarray


def measured_outputs(cm: CompiledModel, outputs: dict[str, float], field: str = "outputs") -> Measured:
    """The rows of `outputs` in the model's output vector.

    Parameters
    ----------
    cm : CompiledModel
        The model.
    outputs : dict
        Output name -> noise standard deviation.
    field : str
        Names the request's field in an error.

    Returns
    -------
    Measured
    """
    from greyfit.solvers.errors import ModelDefinitionError
    missing = [name for name in outputs if name not in cm.outputs]
    if missing:
        raise ModelDefinitionError(
            f"{missing[0]!r} is not an output of model {cm.model.name!r} (its outputs: "
            f"{', '.join(cm.outputs)})", f"{field}.{missing[0]}")
    return Measured(tuple(cm.outputs.index(name) for name in outputs),
                    np.array([outputs[name] for name in outputs], dtype=float))


def _step(cm: CompiledModel, substeps: int) -> ca.Function:
    return make_step(cm, FitOptions(integrator="rk4", substeps=substeps, input_interpolation="zoh"))


def trajectory_function(cm: CompiledModel, n: int, substeps: int, rows: tuple[int, ...]) -> ca.Function:
    """Function (x0, U, p, t, dt) -> Y: the measured outputs at n samples under held inputs.

    Parameters
    ----------
    cm : CompiledModel
        The model.
    n : int
        Number of samples (n - 1 steps).
    substeps : int
        RK4 steps per sample.
    rows : tuple of int
        The measured outputs' rows.

    Returns
    -------
    casadi.Function
        x0 (nx), U (nu × n), p (np), t (1 × n) sample times, dt (1 × n-1) steps -> Y (len(rows) × n).
    """
    def build() -> ca.Function:
        step = _step(cm, substeps)
        x, u, p, t, dt = (ca.SX.sym("x", cm.nx), ca.SX.sym("u", cm.nu), ca.SX.sym("p", cm.np),
                          ca.SX.sym("t"), ca.SX.sym("dt"))
        one = ca.Function("one", [x, u, p, t, dt], [step(x, u, u, p, t, dt)])
        y = cm.output(x, u, p, t)
        out = ca.Function("out", [x, u, p, t], [ca.vertcat(*[y[r] for r in rows])])
        return _assemble(cm, n, one, out, "trajectory")
    return cm.derive(("design_trajectory", n, substeps, rows), build)


def information_function(cm: CompiledModel, n: int, substeps: int, rows: tuple[int, ...],
                         free: tuple[int, ...]) -> ca.Function:
    """Function (x0, U, p, t, dt, w) -> F: the Fisher information of the free parameters.

    Parameters
    ----------
    cm : CompiledModel
        The model.
    n : int
        Number of samples.
    substeps : int
        RK4 steps per sample.
    rows : tuple of int
        The measured outputs' rows.
    free : tuple of int
        Indices of the free parameters in the full parameter vector.

    Returns
    -------
    casadi.Function
        As `trajectory_function`, with w (len(rows)) the outputs' weights 1/σ², returning
        F = Σ_k (∂y_k/∂θ)ᵀ diag(w) (∂y_k/∂θ) (len(free) × len(free)); the initial state is known.
    """
    def build() -> ca.Function:
        step = _step(cm, substeps)
        nth = len(free)
        x, s = ca.SX.sym("x", cm.nx), ca.SX.sym("s", cm.nx * nth)
        u, p, t, dt = ca.SX.sym("u", cm.nu), ca.SX.sym("p", cm.np), ca.SX.sym("t"), ca.SX.sym("dt")
        w = ca.SX.sym("w", len(rows))
        sens = ca.reshape(s, cm.nx, nth)
        xn = step(x, u, u, p, t, dt)
        sn = ca.jacobian(xn, x) @ sens + ca.jacobian(xn, p)[:, list(free)]
        one = ca.Function("one", [ca.vertcat(x, s), u, p, t, dt], [ca.vertcat(xn, ca.vec(sn))])
        y = cm.output(x, u, p, t)
        y = ca.vertcat(*[y[r] for r in rows])
        dy = ca.jacobian(y, x) @ sens + ca.jacobian(y, p)[:, list(free)]
        info = dy.T @ ca.diag(w) @ dy
        out = ca.Function("out", [ca.vertcat(x, s), u, p, t, w], [ca.vec(info)])
        return _assemble(cm, n, one, out, "information", nth=nth, weights=len(rows))
    return cm.derive(("design_information", n, substeps, rows, free), build)


def _assemble(cm: CompiledModel, n: int, one: ca.Function, out: ca.Function, name: str,
              nth: int = 0, weights: int = 0) -> ca.Function:
    """The n-sample graph: `one` accumulated over the steps, `out` mapped over the samples."""
    nxa = cm.nx * (1 + nth)
    x0 = ca.MX.sym("x0", cm.nx)
    U, p = ca.MX.sym("U", cm.nu, n), ca.MX.sym("p", cm.np)
    t, dt = ca.MX.sym("t", 1, n), ca.MX.sym("dt", 1, max(n - 1, 1))
    xa0 = ca.vertcat(x0, ca.MX.zeros(nxa - cm.nx))   # the initial state is known: S(0) = 0
    steps = one.mapaccum("steps", n - 1)
    X = ca.horzcat(xa0, steps(xa0, U[:, :n - 1], ca.repmat(p, 1, n - 1), t[:, :n - 1], dt[:, :n - 1]))
    mapped = out.map(n)
    if nth:
        w = ca.MX.sym("w", weights)
        F = ca.reshape(ca.sum2(mapped(X, U, ca.repmat(p, 1, n), t, ca.repmat(w, 1, n))), nth, nth)
        return ca.Function(name, [x0, U, p, t, dt, w], [F])
    return ca.Function(name, [x0, U, p, t, dt], [mapped(X, U, ca.repmat(p, 1, n), t)])
