"""Model-reference adaptive estimator (seed 003, 7.3): the plant is the reference model.

For a continuous-time model whose right-hand side is affine in the estimated vector η,
dx/dt = f₀(x, u) + G(x, u) η, the adjustable (parallel) model

    dx̂/dt = f₀(x̂, u) + G(x̂, u) η̂,        e = x − x̂,

is driven by the measured input, and η̂ follows the PI adaptation law of eqs. (7-29)/(7-30),

    η̂ = η̂(0) + Kp·s(t) + Ki·∫ s dτ,      s = Gᵀ(x̂, u) e,

which satisfies Popov's integral inequality (the proof in seed 003, example 7-3) when the error
system's linear block is strictly positive real — true for a stable first-order plant (compensator
P = 1); for higher orders seed 003 inserts P from the Lyapunov equation, which needs the unknown A:
only P = I is implemented, so stability is guaranteed when A + Aᵀ < 0. To make the gains
dimensionless the law runs on η scaled by its guess, e by the RMS of each state and every
regressor column by its RMS. The adjustable model is integrated by Euler with `substeps` per
sample, inputs linear between samples. There is no covariance: no band is returned.
"""
from __future__ import annotations

import casadi as ca
import numpy as np

from schemas.online import MrasOptions
from solvers.data import ExperimentData
from solvers.errors import DataError
from solvers.recursive import OnlineRun
from solvers.reparametrize import LinearForm


def model_reference_adaptive(form: LinearForm, d: ExperimentData, ed, equations: list[int], eta0: np.ndarray,
                             opts: MrasOptions) -> OnlineRun:
    """Run the MRAS over the experiment; estimates at the equation-error rows (scaled units)."""
    cm, layout = form.cm, form.layout
    if cm.model.discrete is not None:
        raise DataError("mras is the continuous-time estimator of seed 003; use recursive_least_squares "
                        "for discrete-time models", "method")
    x, u, t = ca.SX.sym("x", cm.nx), ca.SX.sym("u", cm.nu), ca.SX.sym("t")
    eta = ca.SX.sym("eta", layout.size)
    f = cm.rhs(x, u, ca.DM(layout.offset) + ca.DM(layout.matrix[0]) @ eta, t)[equations]
    g = ca.jacobian(f, eta)                                    # G(x, u) in scaled η
    f0 = ca.substitute(f, eta, ca.DM.zeros(layout.size))
    fun = ca.Function("mras_parts", [x, u, t], [f0, g])

    xs = ed.x                                                  # measured states (nx, N)
    rows = ed.rows
    first, last = int(rows[0]), int(rows[-1])
    x_scale = np.array([np.sqrt(np.nanmean(xs[i, rows] ** 2)) or 1.0 for i in equations])
    _, g_all = fun.map(rows.size)(xs[:, rows], d.u[:, rows], d.t[rows][None, :])
    g_all = np.array(g_all).reshape(len(equations), rows.size, layout.size)
    g_scale = np.sqrt(np.mean(g_all ** 2, axis=(0, 1)))
    g_scale[g_scale == 0] = 1.0

    xhat = xs[:, first].copy()
    est = np.array(eta0, dtype=float)
    integral = np.zeros(layout.size)
    estimates = np.empty((rows.size, layout.size))
    errors = np.empty((rows.size, len(equations)))
    row_of = {int(r): k for k, r in enumerate(rows)}
    for k in range(first, last + 1):
        if k in row_of:
            estimates[row_of[k]] = est
            errors[row_of[k]] = xs[equations, k] - xhat[equations]
        if k == last:
            break
        h = (d.t[k + 1] - d.t[k]) / opts.substeps
        for j in range(opts.substeps):
            frac = j / opts.substeps
            uu = d.u[:, k] + frac * (d.u[:, k + 1] - d.u[:, k])
            xm = xs[:, k] + frac * (xs[:, k + 1] - xs[:, k])   # measured states between samples
            xhat_full = xm.copy()
            xhat_full[equations] = xhat[equations]
            f0v, gv = fun(xhat_full, uu, d.t[k] + frac * h * opts.substeps)
            f0v, gv = np.array(f0v).ravel(), np.array(gv)
            e = (xm[equations] - xhat[equations]) / x_scale
            s = (gv / g_scale).T @ e
            integral += h * s
            est = eta0 + opts.kp * s + opts.ki * integral
            xhat[equations] = xhat[equations] + h * (f0v + gv @ est)
    return OnlineRun(estimates, None, errors, f"mras (Popov PI law, kp = {opts.kp:g}, ki = {opts.ki:g})",
                     rows.size, 1.0, measured=xs[equations][:, rows], residual_weighted=False)
