"""Model-reference adaptive estimator (model reference adaptive systems chapter, 7.3): the plant is the reference model.

For a continuous-time model whose right-hand side is affine in the estimated vector η,
dx/dt = f₀(x, u) + G(x, u) η, the adjustable (parallel) model

    dx̂/dt = f₀(x̂, u) + G(x̂, u) η̂,        e = x − x̂,

is driven by the measured input, and η̂ follows the PI adaptation law of eqs. (7-29)/(7-30),

    η̂ = η̂(0) + Kp·s(t) + Ki·∫ s dτ,      s = Gᵀ(x̂, u) e,

which satisfies Popov's integral inequality (the proof in the model reference adaptive systems
chapter, example 7-3) when the error
system's linear block is strictly positive real — true for a stable first-order plant (compensator
P = 1); for higher orders the chapter inserts P from the Lyapunov equation, which needs the unknown A:
only P = I is implemented, so stability is guaranteed when A + Aᵀ < 0. To make the gains
dimensionless the law runs on η scaled by its guess, e by the RMS of each state and every
regressor column by its RMS. The adjustable model and ∫s are integrated together by the fits'
own integrator (RK4 with `substeps` per sample, or CVODES; inputs as `input_interpolation` says,
measured states linear between samples): explicit Euler, as before, biased the induction-motor
speed by +16-33 % at 1 ms sampling. There is no covariance: no band is returned.

Discrete-time models (x[k+1] = f₀ + G η) use the sampled law with the a-posteriori error (Landau's
parallel MRAS), `discrete_model_reference_adaptive` below.
"""
from __future__ import annotations

from dataclasses import dataclass
from types import SimpleNamespace

import casadi as ca
import numpy as np

from greyfit.schemas.fit import FitOptions
from greyfit.schemas.online import MrasOptions
from greyfit.solvers.data.experiments import ExperimentData
from greyfit.solvers.dynamics.integration import make_step
from greyfit.solvers.errors import DataError, ModelDefinitionError
from greyfit.solvers.methods.online.recursive import OnlineRun
from greyfit.solvers.model.discrete import delay_sources
from greyfit.solvers.model.reparametrize import LinearForm


@dataclass
class _ParallelModel:
    """The adjustable model and its adaptation law as one ODE, in the shape `make_step` integrates.

    States (x̂ of the estimated equations, ∫s dτ); inputs the model's; "parameters" the measured
    states at both ends of the interval and its start and length, so the measured states the
    error is formed with are linear between samples whatever the input interpolation.
    """

    model: object
    nx: int
    nu: int
    np: int
    rhs: ca.Function


def _parallel_model(cm, layout, equations: list[int], eta0: np.ndarray, opts: MrasOptions,
                    x_scale: np.ndarray, g_scale: np.ndarray) -> tuple[_ParallelModel, ca.Function]:
    """(the ODE of x̂ and ∫s for `make_step`, Function (x̂, ∫s, x, u, t) -> η̂ at a sample)."""
    neq, n = len(equations), layout.size
    xh, z = ca.SX.sym("xhat", neq), ca.SX.sym("z", n)
    u, t = ca.SX.sym("u", cm.nu), ca.SX.sym("t")
    xa, xb, t0, dt = ca.SX.sym("xa", cm.nx), ca.SX.sym("xb", cm.nx), ca.SX.sym("t0"), ca.SX.sym("dt")
    frac = (t - t0) / dt
    xm = xa + frac * (xb - xa)                                 # measured states between samples
    full = ca.vertcat(*[xh[equations.index(i)] if i in equations else xm[i] for i in range(cm.nx)])
    eta = ca.SX.sym("eta", n)
    f = cm.rhs(full, u, ca.DM(layout.offset) + ca.DM(layout.matrix[0]) @ eta, t)[equations]
    g = ca.substitute(ca.jacobian(f, eta), eta, ca.DM.zeros(n))   # f is affine in η: G(x̂, u)
    s = (g @ ca.diag(ca.DM(1.0 / g_scale))).T @ ((xm[equations] - xh) / ca.DM(x_scale))
    est = ca.DM(eta0) + opts.kp * s + opts.ki * z
    ode = ca.vertcat(ca.substitute(f, eta, est), s)
    state, params = ca.vertcat(xh, z), ca.vertcat(xa, xb, t0, dt)
    rhs = ca.Function("mras_rhs", [state, u, params, t], [ode])
    at_sample = ca.Function("mras_estimate", [state, xa, u, t],
                            [ca.substitute(est, ca.vertcat(xb, t0, dt), ca.vertcat(xa, t, 1.0))])
    return _ParallelModel(SimpleNamespace(discrete=None), neq + n, cm.nu, 2 * cm.nx + 2, rhs), at_sample


def model_reference_adaptive(form: LinearForm, d: ExperimentData, ed, equations: list[int], eta0: np.ndarray,
                             opts: MrasOptions, fit_options: FitOptions | None = None) -> OnlineRun:
    """Run the MRAS over the experiment; estimates at the equation-error rows (scaled units).

    The adjustable model and the integral of the adaptation law are integrated together by the
    fits' own one-sample integrator (`solvers.dynamics.integration.make_step`: RK4 with
    `opts.substeps` steps per sample, or CVODES), inputs interpolated as `fit_options` says.
    Discrete-time models are handed to `discrete_model_reference_adaptive`.

    Parameters
    ----------
    form : LinearForm
        The model in its linear coefficients η (`solvers.model.reparametrize.linear_form`).
    d : ExperimentData
        The one prepared experiment (time, inputs, measured states).
    ed : object
        Equation error's per-experiment data of that experiment: states `x` (nx, N), next values `dx`
        and the `rows` (sample indices) the estimates are returned at.
    equations : list of int
        Indices of the estimated state equations (those that depend on a free parameter).
    eta0 : numpy.ndarray
        (nη,) initial estimate η̂(0), scaled units.
    opts : MrasOptions
        Adaptation gains `kp`, `ki`, `substeps` per sample.
    fit_options : FitOptions or None
        The fit's options (integrator, input interpolation); None: the defaults.

    Returns
    -------
    OnlineRun
        Estimates (M, nη) at the rows, no covariances, the state errors x − x̂ (M, neq) as innovations and
        the measured states they are errors of; window M, memory 1.

    Raises
    ------
    DataError, ModelDefinitionError
        From `discrete_model_reference_adaptive` for a discrete-time model.
    """
    cm, layout = form.cm, form.layout
    if cm.model.discrete is not None:
        return discrete_model_reference_adaptive(form, d, ed, equations, eta0, opts)
    fit_options = fit_options or FitOptions()
    xs, rows = ed.x, ed.rows
    first, last = int(rows[0]), int(rows[-1])
    x_scale = np.array([np.sqrt(np.nanmean(xs[i, rows] ** 2)) or 1.0 for i in equations])
    g_scale = _regressor_scale(cm, layout, equations, xs[:, rows], d.u[:, rows], d.t[rows])
    parallel, at_sample = _parallel_model(cm, layout, equations, np.asarray(eta0, float), opts, x_scale, g_scale)
    # a stand-in model: make_step integrates anything with model.discrete, nx, nu, np and rhs
    step = make_step(parallel, fit_options.model_copy(update={"substeps": opts.substeps}))  # type: ignore[arg-type]
    k = np.arange(first, last)
    params = np.vstack([xs[:, k], xs[:, k + 1], d.t[k][None, :], (d.t[k + 1] - d.t[k])[None, :]])
    start = np.concatenate([xs[equations, first], np.zeros(layout.size)])
    traj = np.array(step.mapaccum(k.size)(start, d.u[:, k], d.u[:, k + 1], params, d.t[k][None, :],
                                          (d.t[k + 1] - d.t[k])[None, :]))
    states = np.column_stack([start, traj])                       # at samples first..last
    samples = np.arange(first, last + 1)
    est = np.array(at_sample.map(samples.size)(states, xs[:, samples], d.u[:, samples], d.t[samples][None, :]))
    pick = rows - first
    errors = (xs[equations][:, rows] - states[:len(equations), pick]).T
    return OnlineRun(est[:, pick].T, None, errors, f"mras (Popov PI law, kp = {opts.kp:g}, ki = {opts.ki:g})",
                     rows.size, 1.0, measured=xs[equations][:, rows], residual_weighted=False)


def _regressor_scale(cm, layout, equations, x, u, t) -> np.ndarray:
    """RMS of every column of G(x, u) over the measured states: makes the gains dimensionless."""
    xx, uu, tt = ca.SX.sym("x", cm.nx), ca.SX.sym("u", cm.nu), ca.SX.sym("t")
    eta = ca.SX.sym("eta", layout.size)
    f = cm.rhs(xx, uu, ca.DM(layout.offset) + ca.DM(layout.matrix[0]) @ eta, tt)[equations]
    g = ca.Function("mras_g", [xx, uu, tt], [ca.jacobian(f, eta)])
    g_all = np.array(g.map(x.shape[1])(x, u, t[None, :])).reshape(len(equations), x.shape[1], layout.size)
    scale = np.sqrt(np.mean(g_all ** 2, axis=(0, 1)))
    scale[scale == 0] = 1.0
    return scale


class _DiscreteParts:
    """f = f₀(x, u) + G(x, u) η and the full f, as numpy when f is bilinear in (x, u) and η
    (every linear-coefficient form is), else through CasADi calls (slower per sample)."""

    def __init__(self, form: LinearForm, equations: list[int]):
        cm, layout = form.cm, form.layout
        x, u, t = ca.SX.sym("x", cm.nx), ca.SX.sym("u", cm.nu), ca.SX.sym("t")
        eta = ca.SX.sym("eta", layout.size)
        z = ca.vertcat(x, u)
        f = cm.rhs(x, u, ca.DM(layout.offset) + ca.DM(layout.matrix[0]) @ eta, t)
        self.eq = equations
        g = ca.jacobian(f[equations], eta)
        self.casadi_parts = ca.Function("mras_parts", [x, u, t], [ca.substitute(f[equations], eta, 0 * eta), g])
        self.casadi_full = ca.Function("f_all", [x, u, t, eta], [f])
        jz, je = ca.jacobian(f, z), ca.jacobian(f, eta)
        self.bilinear = not (ca.depends_on(ca.vertcat(ca.vec(jz), ca.vec(je)), t)
                             or ca.depends_on(jz, z) or ca.depends_on(je, eta))
        if self.bilinear:
            zero_z, zero_e = ca.DM.zeros(z.shape), ca.DM.zeros(eta.shape)
            ev = lambda expr: np.array(ca.evalf(ca.substitute(ca.substitute(expr, z, zero_z), eta, zero_e)))
            self.k0 = ev(f).ravel()
            self.jz0, self.je0 = ev(jz), ev(je)
            # ∂²f/∂z∂η: column j of ∂f/∂η is affine in z
            self.t = np.stack([ev(ca.jacobian(je[:, j], z)) for j in range(layout.size)], axis=2)   # (nx, nz, nη)

    def parts(self, x, u, t):
        if not self.bilinear:
            f0, g = self.casadi_parts(x, u, t)
            return np.array(f0).ravel(), np.array(g)
        z = np.concatenate([x, u])
        f0 = self.k0[self.eq] + self.jz0[self.eq] @ z
        return f0, self.je0[self.eq] + np.einsum("ijk,j->ik", self.t[self.eq], z)

    def full(self, x, u, t, eta):
        if not self.bilinear:
            return np.array(self.casadi_full(x, u, t, eta)).ravel()
        z = np.concatenate([x, u])
        return self.k0 + self.jz0 @ z + (self.je0 + np.einsum("ijk,j->ik", self.t, z)) @ eta


def _following(cm, equations: list[int]) -> list[int]:
    """Delay states of estimated states (y_1 = y[k-1]): the parallel model shifts its own output."""
    sources = delay_sources(cm)
    out = []
    for j in range(cm.nx):
        seen, i = set(), j
        while i in sources and sources[i][0] == "state" and i not in seen and i not in equations:
            seen.add(i)
            i = sources[i][1]
        if j not in equations and i in equations:
            out.append(j)
    return out


def discrete_model_reference_adaptive(form: LinearForm, d: ExperimentData, ed, equations: list[int],
                                      eta0: np.ndarray, opts: MrasOptions) -> OnlineRun:
    """Run the MRAS on a discrete-time model: Landau's parallel model with a-posteriori errors.

    The model reference adaptive systems chapter's law, sampled.

    With x[k+1] = f₀ + G η, the adjustable model x̂ runs on its own states (and on its own delayed
    outputs); the PI law of (7-29/30), sampled, is

        η̂_I[k+1] = η̂_I[k] + F_I Gᵀ ε[k+1],   η̂[k+1] = η̂_I[k+1] + F_P Gᵀ ε[k+1],
        ε[k+1] = x[k+1] − f₀ − G η̂[k+1]          (the a-posteriori error, G = G(x̂[k], u[k])),

    solved in closed form, ε = (I + G (F_I + F_P) Gᵀ)⁻¹ (x[k+1] − f₀ − G η̂_I[k]). F_I = ki·Ts,
    F_P = kp. Using ε a posteriori makes the error system's linear block z(zI − A)⁻¹ (a first-order
    plant: z/(z − a)), which is strictly positive real for |a| < 1: Popov's inequality then holds for
    any positive gains (Landau's discrete-time hyperstability design), where the a-priori error of a
    direct transcription would need small gains. Signals are normalised as in continuous time.

    Parameters
    ----------
    form : LinearForm
        The model in its linear coefficients η.
    d : ExperimentData
        The one prepared experiment.
    ed : object
        Equation error's per-experiment data: states `x` (nx, N), next values `dx` (nx, N), `rows`.
    equations : list of int
        Indices of the estimated state equations.
    eta0 : numpy.ndarray
        (nη,) initial estimate, scaled units.
    opts : MrasOptions
        Adaptation gains `kp` (F_P) and `ki` (F_I = ki·Ts).

    Returns
    -------
    OnlineRun
        Estimates (M, nη) before each update at the rows, no covariances, the a-priori state errors
        (M, neq) as innovations; window M, memory 1.

    Raises
    ------
    DataError
        When the rows are not consecutive samples (`experiments[0].outputs` has gaps).
    ModelDefinitionError
        When the model is not discrete-time (`model.discrete`).
    """
    cm, layout = form.cm, form.layout
    model = _DiscreteParts(form, equations)
    follow = _following(cm, equations)
    xs, nxt, rows = ed.x, ed.dx, ed.rows
    first, last = int(rows[0]), int(rows[-1])
    if not np.all(np.diff(rows) == 1):
        raise DataError("the discrete-time MRAS runs over consecutive samples; this record has gaps",
                        "experiments[0].outputs")
    x_scale = np.array([np.sqrt(np.nanmean(xs[i, rows] ** 2)) or 1.0 for i in equations])
    _, g_all = model.casadi_parts.map(rows.size)(xs[:, rows], d.u[:, rows], d.t[rows][None, :])
    psi_all = np.array(g_all).reshape(len(equations), rows.size, layout.size) / x_scale[:, None, None]
    psi_rms = np.sqrt(np.mean(psi_all ** 2, axis=(0, 1)))
    psi_rms[psi_rms == 0] = 1.0
    if cm.model.discrete is None:
        raise ModelDefinitionError("the discrete-time MRAS needs a discrete-time model", "model.discrete")
    ts = cm.model.discrete.sample_time
    f_i, f_p = opts.ki * ts, opts.kp

    xhat = xs[:, first].copy()
    eta_i = np.array(eta0, dtype=float)
    est = eta_i.copy()
    estimates = np.empty((rows.size, layout.size))
    errors = np.empty((rows.size, len(equations)))
    for r, k in enumerate(range(first, last + 1)):
        estimates[r] = est
        errors[r] = xs[equations, k] - xhat[equations]
        f0v, gv = model.parts(xhat, d.u[:, k], d.t[k])
        psi = gv / x_scale[:, None] / psi_rms                      # normalised regressor Ψ̄ (neq × nη)
        prior = (nxt[equations, k] - f0v - gv @ eta_i) / x_scale
        gram = (f_i + f_p) * psi @ psi.T
        eps = prior / (1 + gram[0, 0]) if gram.shape == (1, 1) else np.linalg.solve(np.eye(len(gram)) + gram, prior)
        step = (psi.T @ eps) / psi_rms                              # F = f·diag(1/ψ_rms²) on Ψ = G/x_scale
        eta_i = eta_i + f_i * step
        est = eta_i + f_p * step
        full = model.full(xhat, d.u[:, k], d.t[k], est)
        new = nxt[:, k].copy()
        new[equations] = nxt[equations, k] - eps * x_scale         # x̂[k+1] = x[k+1] − ε[k+1]
        new[follow] = full[follow]
        xhat = new
    return OnlineRun(estimates, None, errors, f"mras (discrete time, Landau a-posteriori PI law, kp = {opts.kp:g}, "
                     f"ki = {opts.ki:g})", rows.size, 1.0, measured=xs[equations][:, rows], residual_weighted=False)
