"""One-sample integrator Functions: fixed-step RK4 (expanded to SX) or CVODES for stiff models.

Each integrator is a record (`INTEGRATORS`) that says what it supports, so the rest of the code asks
`integrator_of(options).fixed_step` (is there a step size to judge and refine with substeps?) or
`.symbolic` (does the step expand to SX: compiled kernels, the structured shooting form, SX
sensitivities?) instead of comparing names. A new integrator is one builder and one entry.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import casadi as ca

from greyfit.schemas.fit import FitOptions
from greyfit.solvers.model.compiler import CompiledModel


def _input_at(u0, u1, tau, interpolation: str):
    """Input at fraction tau of the interval: held (zoh) or linear (foh; also an unresolved "auto")."""
    return u0 if interpolation == "zoh" else u0 + (u1 - u0) * tau


def make_step(cm: CompiledModel, options: FitOptions) -> ca.Function:
    """Function step(x, u0, u1, p, t0, dt) -> x(t0 + dt), built once per model and options.

    Cached on the compiled model under the integrator, substeps and input interpolation; a stand-in
    model (not a `CompiledModel`) gets a fresh one each call.

    Parameters
    ----------
    cm : CompiledModel
        The compiled model (or a stand-in with the same interface).
    options : FitOptions
        Fit options; `integrator`, `substeps` and `input_interpolation` shape the step.

    Returns
    -------
    casadi.Function
        The one-interval step: the inputs at the interval's ends u0, u1, parameters p, start time t0
        and interval length dt map the state x to the state at t0 + dt. For a discrete-time model,
        the difference equation itself.
    """
    if not isinstance(cm, CompiledModel):   # a stand-in (e.g. discovery's disturbed model)
        return _make_step(cm, options)
    key = ("step", options.integrator, options.substeps, options.input_interpolation)
    return cm.derive(key, lambda: _make_step(cm, options))


def _make_step(cm: CompiledModel, options: FitOptions) -> ca.Function:
    if cm.model.discrete is not None:   # difference equation: the step is f itself
        from greyfit.solvers.model.discrete import make_discrete_step
        return make_discrete_step(cm)
    return integrator_of(options).build(cm, options)


def _rk4_step(cm: CompiledModel, options: FitOptions) -> ca.Function:
    x = ca.SX.sym("x", cm.nx)
    u0, u1 = ca.SX.sym("u0", cm.nu), ca.SX.sym("u1", cm.nu)
    p, t0, dt = ca.SX.sym("p", cm.np), ca.SX.sym("t0"), ca.SX.sym("dt")
    n = options.substeps
    h = dt / n
    xk = x
    for i in range(n):
        def f(xx, frac):
            return cm.rhs(xx, _input_at(u0, u1, frac, options.input_interpolation), p,
                          t0 + frac * dt)
        a = i / n
        k1 = f(xk, a)
        k2 = f(xk + h / 2 * k1, a + 0.5 / n)
        k3 = f(xk + h / 2 * k2, a + 0.5 / n)
        k4 = f(xk + h * k3, a + 1.0 / n)
        xk = xk + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return ca.Function("step", [x, u0, u1, p, t0, dt], [xk]).expand()


def _cvodes_step(cm: CompiledModel, options: FitOptions) -> ca.Function:
    # CVODES on normalised time tau in [0, 1] so that one Function serves every interval length.
    x = ca.SX.sym("x", cm.nx)
    u0, u1 = ca.SX.sym("u0", cm.nu), ca.SX.sym("u1", cm.nu)
    p, t0, dt = ca.SX.sym("p", cm.np), ca.SX.sym("t0"), ca.SX.sym("dt")
    tau = ca.SX.sym("tau")
    params = ca.vertcat(u0, u1, p, t0, dt)
    ode = dt * cm.rhs(x, _input_at(u0, u1, tau, options.input_interpolation), p, t0 + tau * dt)
    integ = ca.integrator("cvodes_step", "cvodes", {"x": x, "p": params, "t": tau, "ode": ode},
                          0.0, 1.0, {"abstol": 1e-10, "reltol": 1e-8})
    xm = ca.MX.sym("x", cm.nx)
    u0m, u1m = ca.MX.sym("u0", cm.nu), ca.MX.sym("u1", cm.nu)
    pm, t0m, dtm = ca.MX.sym("p", cm.np), ca.MX.sym("t0"), ca.MX.sym("dt")
    xf = integ(x0=xm, p=ca.vertcat(u0m, u1m, pm, t0m, dtm))["xf"]
    return ca.Function("step", [xm, u0m, u1m, pm, t0m, dtm], [xf])


@dataclass(frozen=True)
class Integrator:
    """What an integrator supports.

    fixed_step : a step h = dt / substeps whose accuracy is judged by the fastest mode's |λ|·h
        (and refined by raising `options.substeps`); False for adaptive ones.
    symbolic : the step expands to SX, so kernels compile to C, shooting takes its structured form and
        the exact Hessian is differentiation of an expression (not second-order sensitivities: the
        exact-Hessian polish of `solvers.methods.multistart` runs only then).
    """

    name: str
    fixed_step: bool
    symbolic: bool
    build: Callable[[CompiledModel, FitOptions], ca.Function]


INTEGRATORS: dict[str, Integrator] = {i.name: i for i in (
    Integrator("rk4", fixed_step=True, symbolic=True, build=_rk4_step),
    Integrator("cvodes", fixed_step=False, symbolic=False, build=_cvodes_step),
)}


def integrator_of(options: FitOptions) -> Integrator:
    """The record of the integrator `options` name.

    Parameters
    ----------
    options : FitOptions
        Fit options; `integrator` names the integrator.

    Returns
    -------
    Integrator
        Its entry in `INTEGRATORS` (whether it is fixed-step and symbolic, and its step builder).
    """
    return INTEGRATORS[options.integrator]
