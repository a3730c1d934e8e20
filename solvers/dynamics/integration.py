"""One-sample integrator Functions: fixed-step RK4 (expanded to SX) or CVODES for stiff models."""
from __future__ import annotations

import casadi as ca

from greyfit.schemas.fit import FitOptions
from greyfit.solvers.model.compiler import CompiledModel


def _input_at(u0, u1, tau, interpolation: str):
    """Input at fraction tau of the interval: held (zoh) or linear (foh; also an unresolved "auto")."""
    return u0 if interpolation == "zoh" else u0 + (u1 - u0) * tau


def make_step(cm: CompiledModel, options: FitOptions) -> ca.Function:
    """Function step(x, u0, u1, p, t0, dt) -> x(t0 + dt), built once per model and options."""
    if not isinstance(cm, CompiledModel):   # a stand-in (e.g. discovery's disturbed model)
        return _make_step(cm, options)
    key = ("step", options.integrator, options.substeps, options.input_interpolation)
    return cm.derive(key, lambda: _make_step(cm, options))


def _make_step(cm: CompiledModel, options: FitOptions) -> ca.Function:
    if cm.model.discrete is not None:   # difference equation: the step is f itself
        from greyfit.solvers.model.discrete import make_discrete_step
        return make_discrete_step(cm)
    x = ca.SX.sym("x", cm.nx)
    u0, u1 = ca.SX.sym("u0", cm.nu), ca.SX.sym("u1", cm.nu)
    p, t0, dt = ca.SX.sym("p", cm.np), ca.SX.sym("t0"), ca.SX.sym("dt")
    if options.integrator == "rk4":
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

    # CVODES on normalised time tau in [0, 1] so that one Function serves every interval length.
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
