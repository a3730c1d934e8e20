"""Linear coefficients of a model and the way back to its physical parameters (delta method).

Online estimators (RLS, MRAS) need a model linear in what they estimate. When the equations are
affine in the free parameters θ they estimate θ itself. Otherwise, if the equations are linear in
the states and inputs (an LTI model such as seed 003's x[k+1] = (1 − T R/L) x[k] + T/L u[k]),
they estimate the θ-dependent coefficients η = c(θ) of the states, inputs and constant term —
(a, b) for the RL circuit — and θ is recovered by weighted Gauss-Newton on η̂ = c(θ), with
Σ_θ = G Σ_η Gᵀ, G = (CᵀWC)⁻¹CᵀW, C = ∂c/∂θ (the delta method; W = Σ_η⁻¹ when it exists).
"""
from __future__ import annotations

from dataclasses import dataclass, replace

import casadi as ca
import numpy as np

from greyfit.solvers.errors import ModelDefinitionError
from greyfit.solvers.model.compiler import CompiledModel
from greyfit.solvers.model.parameters import ParameterLayout, nominal_scale

GN_ITERATIONS = 30


@dataclass
class LinearForm:
    """What the online estimator estimates: θ itself (mapped=False) or coefficients η = c(θ)."""

    cm: CompiledModel            # rhs in the estimated vector (η or θ)
    layout: ParameterLayout      # of the estimated vector
    mapped: bool
    coefficients: ca.Function | None = None   # θ (physical, free) -> (η, ∂η/∂θ)
    descriptions: dict[str, str] | None = None


def _affine(expr: ca.SX, sym: ca.SX) -> bool:
    return not ca.depends_on(ca.jacobian(expr, sym), sym)


def linear_form(cm: CompiledModel, layout: ParameterLayout, equations: list[int]) -> LinearForm:
    """θ when the equations are affine in θ, else the LTI coefficients η = c(θ).

    Parameters
    ----------
    cm : CompiledModel
        The compiled model.
    layout : ParameterLayout
        Layout of the free parameters θ (the first experiment's map is used).
    equations : list of int
        Indices of the state equations the estimator uses.

    Returns
    -------
    LinearForm
        With ``mapped=False`` the model and layout unchanged; else a model whose parameters are the
        θ-dependent coefficients ``c_<state>_<regressor>`` of the states, inputs and constant term
        (started at their values for the initial θ), its layout, and the map θ -> (η, ∂η/∂θ).

    Raises
    ------
    ModelDefinitionError
        When the equations are neither affine in θ nor linear in the states and inputs
        (``model.equations``), or have fewer θ-dependent coefficients than free parameters
        (``model.parameters``).
    """
    x, u, t = ca.SX.sym("x", cm.nx), ca.SX.sym("u", cm.nu), ca.SX.sym("t")
    theta = ca.vertcat(*[ca.SX.sym(label) for label in layout.labels])   # physical free parameters
    p = ca.DM(layout.offset) + ca.DM(layout.matrix[0]) @ (theta / ca.DM(layout.scale))
    f = cm.rhs(x, u, p, t)
    if _affine(f[equations], theta):
        return LinearForm(cm, layout, False)
    z = ca.vertcat(x, u)
    big = ca.horzcat(ca.jacobian(f, z), ca.substitute(f, z, ca.DM.zeros(z.shape)))   # [A B | c0]
    if ca.depends_on(big[equations, :], ca.vertcat(z, t)):
        raise ModelDefinitionError(
            "recursive estimators need equations linear in the free parameters, or linear in the "
            "states and inputs (then their coefficients are estimated and mapped back); this model "
            "is neither. Use equation_error or a shooting method", "model.equations")
    regressors = [*cm.states, *cm.inputs, "1"]
    entries, names, texts = [], [], {}
    for i in equations:
        for j in range(big.size2()):
            if ca.depends_on(big[i, j], theta):
                entries.append((i, j))
                name = f"c_{cm.states[i]}_{regressors[j]}"
                names.append(name)
                texts[name] = f"coefficient of {regressors[j]} in equations.{cm.states[i]}: {big[i, j]}"
    if len(entries) < layout.size:
        raise ModelDefinitionError(
            f"{layout.size} free parameters enter through only {len(entries)} coefficients "
            f"({', '.join(names)}); they cannot all be recovered. Fix some parameters",
            "model.parameters")
    eta_expr = ca.vertcat(*[big[i, j] for i, j in entries])
    coefficients = ca.Function("coefficients", [theta], [eta_expr, ca.jacobian(eta_expr, theta)])
    eta0 = np.array(coefficients(layout.initial)[0]).ravel()

    # rhs in η: the θ-dependent entries replaced by η, everything else as declared
    eta = ca.SX.sym("eta", len(entries))
    rows = [f[i] for i in range(cm.nx)]
    zz = ca.vertcat(z, 1)
    for i in equations:
        known = ca.substitute(f[i], theta, ca.DM(layout.initial))
        for k, (ii, j) in enumerate(entries):
            if ii == i:
                known = known - ca.substitute(big[i, j], theta, ca.DM(layout.initial)) * zz[j] + eta[k] * zz[j]
        rows[i] = known
    rhs = ca.Function("rhs_eta", [x, u, eta, t], [ca.substitute(ca.vertcat(*rows), theta, ca.DM(layout.initial))],
                      ["x", "u", "p", "t"], ["dx"])
    cm_eta = replace(cm, rhs=rhs, parameters=names)
    scale = np.array([nominal_scale(float(v), None, None) for v in eta0])
    n = len(names)
    layout_eta = ParameterLayout(
        labels=names, base_names=names, experiment=[None] * n, scale=scale, initial=eta0,
        lower=np.full(n, -np.inf), upper=np.full(n, np.inf), offset=np.zeros(n),
        matrix=[np.diag(scale)], fixed={})
    return LinearForm(cm_eta, layout_eta, True, coefficients, texts)


def _coefficients(form: LinearForm) -> ca.Function:
    if form.coefficients is None:
        raise TypeError("this linear form estimates θ itself: it has no coefficient map")
    return form.coefficients


def _gauss_newton(form: LinearForm, eta: np.ndarray, weight: np.ndarray, theta0: np.ndarray) -> np.ndarray:
    """θ (nθ, M) minimising (η − c(θ))ᵀW(η − c(θ)) column by column, all columns at once.

    Gauss-Newton with step halving: c(θ) is often a ratio (T/L), where a full step can overshoot.
    """
    m, n = eta.shape[1], theta0.shape[0]
    f = _coefficients(form).map(m)
    theta = np.array(theta0, dtype=float)

    def evaluate(th):
        c, jac = f(th)
        r = (eta - np.array(c)).T                                                       # (m, nη)
        cost = np.einsum("mi,ij,mj->m", r, weight, r)
        return r, np.array(jac).reshape(eta.shape[0], m, n).transpose(1, 0, 2), cost    # jac (m, nη, nθ)

    r, jac, cost = evaluate(theta)
    for _ in range(GN_ITERATIONS):
        jw = jac.transpose(0, 2, 1) @ weight                                             # (m, nθ, nη)
        with np.errstate(all="ignore"):
            step = np.linalg.solve(jw @ jac + 1e-12 * np.eye(n), jw @ r[:, :, None])[..., 0].T
        step = np.where(np.isfinite(step), step, 0.0)
        alpha = np.ones(m)
        for _ in range(30):
            trial = theta + alpha * step
            r_t, jac_t, cost_t = evaluate(trial)
            worse = ~(cost_t <= cost) & (alpha > 1e-9)
            if not worse.any():
                break
            alpha = np.where(worse, alpha / 2, alpha)
        better = cost_t <= cost
        theta = np.where(better, trial, theta)
        r = np.where(better[:, None], r_t, r)
        jac = np.where(better[:, None, None], jac_t, jac)
        done = np.all(np.abs(alpha * step) <= 1e-12 * np.maximum(np.abs(theta), 1e-300)) or np.allclose(cost, cost_t)
        cost = np.where(better, cost_t, cost)
        if done:
            break
    return theta


def to_physical(form: LinearForm, eta: np.ndarray, cov_eta: np.ndarray | None, theta_start: np.ndarray,
                weight_cov: np.ndarray | None = None):
    """Physical θ for each column of η (nη, M) and its covariance (M, nθ, nθ) by the delta method.

    `cov_eta` (M, nη, nη) or None; `weight_cov` is the covariance whose inverse weights the fit
    (the final one, so that every sample is mapped the same way); `theta_start` (nθ,) or (nθ, M).

    Parameters
    ----------
    form : LinearForm
        A mapped linear form (with its coefficient map).
    eta : numpy.ndarray
        Coefficient estimates, one column per sample, shape (nη, M).
    cov_eta : numpy.ndarray or None
        Their covariances, shape (M, nη, nη).
    theta_start : numpy.ndarray
        Start of the Gauss-Newton fit, shape (nθ,) or (nθ, M).
    weight_cov : numpy.ndarray or None, optional
        Covariance whose inverse weights the fit; when missing, not finite or ill-conditioned
        (condition ≥ 1e14), the weight is diag(1/scale²) of the form's layout.

    Returns
    -------
    theta : numpy.ndarray
        Physical parameters per column, shape (nθ, M).
    cov_theta : numpy.ndarray or None
        Their covariances G Σ_η Gᵀ, shape (M, nθ, nθ); None without `cov_eta` or when CᵀWC is singular.

    Raises
    ------
    TypeError
        When `form` estimates θ itself (it has no coefficient map).
    """
    n_eta, m = eta.shape
    if weight_cov is not None and np.all(np.isfinite(weight_cov)) and np.linalg.cond(weight_cov) < 1e14:
        weight = np.linalg.inv(weight_cov)
    else:
        weight = np.diag(1.0 / form.layout.scale ** 2)
    start = np.broadcast_to(np.reshape(theta_start, (-1, 1)) if np.ndim(theta_start) == 1 else theta_start,
                            (len(theta_start) if np.ndim(theta_start) == 1 else theta_start.shape[0], m))
    theta = _gauss_newton(form, eta, weight, start)
    if cov_eta is None:
        return theta, None
    _, jac = _coefficients(form).map(m)(theta)
    jac = np.array(jac).reshape(n_eta, m, theta.shape[0]).transpose(1, 0, 2)
    jw = jac.transpose(0, 2, 1) @ weight
    with np.errstate(all="ignore"):
        try:
            g = np.linalg.solve(jw @ jac, jw)                          # (m, nθ, nη)
        except np.linalg.LinAlgError:
            return theta, None
    return theta, g @ cov_eta @ g.transpose(0, 2, 1)
