"""Start a confirming refit where the screen says the answer is: one Gauss-Newton step of the
augmented fit.

The screen regressed the residual r on the candidate's column(s) g with the existing parameters'
sensitivities J projected out: that is the Gauss-Newton step of the augmented least-squares
problem, β for the new term and δθ = J⁺(r − g β) for the declared parameters. Starting the refit
there instead of at the old fit with the new parameter at zero
- saves Ipopt iterations (a friction that the damping had absorbed moves both at once), and
- gives the new parameter a scale: started at 0 (or 1e-6 against a lower bound of 0) its nominal
  scale is that tiny number, and the solver works in a badly scaled variable.

β is a coefficient on ẋ (or on y for output-path effects); the model's parameter enters as
sign·p·term/denominator, so p = β/κ with κ = ∂f/∂p / g along the fitted trajectory, evaluated on
the new model. The step is shortened so that no declared parameter moves by more than half its
size (the linearisation is only trusted that far), and everything is clipped to the bounds. Any
failure falls back to the plain warm start (old fit, new parameter at its neutral value), and so
does a step whose model cannot be simulated over the records (`start_is_sound`): a destabilising
term (+β v³ with β > 0) blows up in finite time, and a multiple-shooting refit started there has
gaps of 1e196 whose first Ipopt iteration took 34 s of CPU in the linear solver (the neutral start:
converged in 0.7 s).
"""
from __future__ import annotations

import casadi as ca
import numpy as np

from greyfit.schemas.fit import FitRequest, FitResult
from greyfit.schemas.model import Model
from greyfit.solvers.model.compiler import compile_model
from greyfit.solvers.screening.scoring import RegressionScorer

MAX_RELATIVE_MOVE = 0.5
START_MAX_RMSE_RATIO = 10.0   # a start whose simulation misses the records by more than this × the fit's: unsound


def gauss_newton_start(scorer: RegressionScorer, candidate, fit: FitResult, model: Model,
                       new_params: list[str]) -> Model:
    """`model` (the augmented one, declared parameters at the old fit) with initial values one
    Gauss-Newton step away; `model` unchanged when the step cannot be formed.

    Parameters
    ----------
    scorer : RegressionScorer
        The regression the candidate was scored in (residual, Jacobian, trajectories).
    candidate : Candidate
        The candidate being refitted.
    fit : FitResult
        The fit the candidate was screened at.
    model : Model
        The augmented model, its declared parameters at the old fit's estimates.
    new_params : list of str
        Names of the parameters the candidate added, one per column.

    Returns
    -------
    Model
        A copy with the initial values of the free shared parameters moved by the (shortened) step and
        clipped to their bounds; a new parameter whose step lands on a bound keeps its neutral start.
    """
    try:
        values = _step(scorer, candidate, fit, model, new_params)
    except (RuntimeError, ValueError, np.linalg.LinAlgError, KeyError, IndexError):
        return model
    if not values:
        return model
    params = []
    for p in model.parameters:
        if p.name not in values or p.fixed or p.per_experiment:
            params.append(p)
            continue
        lo = -np.inf if p.lower is None else p.lower
        hi = np.inf if p.upper is None else p.upper
        v = float(np.clip(values[p.name], lo, hi))
        if p.name in new_params and (v == lo or v == hi):
            params.append(p)   # the step points out of the bounds (wrong sign): keep the neutral start
            continue
        params.append(p.model_copy(update={"value": v}))
    return model.model_copy(update={"parameters": params})


def _step(scorer: RegressionScorer, candidate, fit: FitResult, model: Model,
          new_params: list[str]) -> dict[str, float]:
    g = scorer.stack(candidate.equations, candidate.outputs)
    if g is None or not new_params or not np.all(np.isfinite(g)):
        return {}
    g = g.reshape(g.shape[0], -1)
    if g.shape[1] != len(new_params):
        return {}
    g0 = scorer.project(g)
    beta, *_ = np.linalg.lstsq(g0, scorer.r0, rcond=None)
    delta, *_ = np.linalg.lstsq(scorer.jac, scorer.r - g @ beta, rcond=None)
    moves = scorer.parameter_moves(delta)            # declared name -> physical change
    kappa = _coefficient_scale(scorer, candidate, fit, model, new_params)
    if kappa is None:
        return {}
    new_values = {n: float(b / k) for n, b, k in zip(new_params, beta, kappa)}
    alpha = 1.0
    for name, d in moves.items():
        est = fit.parameters.get(name)
        if est is None or d == 0:
            continue
        size = max(abs(est.value), 1e-12)
        alpha = min(alpha, MAX_RELATIVE_MOVE * size / abs(d))
    out = {n: fit.parameters[n].value + alpha * d for n, d in moves.items() if n in fit.parameters}
    out.update({n: alpha * v for n, v in new_values.items()})
    return out


def _coefficient_scale(scorer: RegressionScorer, candidate, fit: FitResult, model: Model,
                       new_params: list[str]) -> list[float] | None:
    """κ_j: how the new model's parameter j scales the candidate's column j (1 for output-path
    effects and for parameters that vary in time, whose columns are ∂f/∂θ · shape already)."""
    if not candidate.equations:
        return [1.0] * len(new_params)
    cm = compile_model(model)
    x, u, p, t = ca.SX.sym("x", cm.nx), ca.SX.sym("u", cm.nu), ca.SX.sym("p", cm.np), ca.SX.sym("t")
    idx = [cm.parameters.index(n) for n in new_params]
    jac = ca.Function("dfdp", [x, u, p, t], [ca.jacobian(cm.rhs(x, u, p, t), p)[:, idx]])
    num = np.zeros(len(new_params))
    den = np.zeros(len(new_params))
    for e, (states, inputs, times, name) in enumerate(scorer.trajectories()):
        n = times.size
        pvec = np.array([_value(fit, prm, name) for prm in model.parameters])
        pvec[idx] = 0.0
        d = np.array(jac.map(n)(states, inputs, np.repeat(pvec[:, None], n, 1), times[None, :]))
        d = d.reshape(cm.nx, n, len(idx))
        for i, cols in candidate.equations.items():
            col = np.reshape(cols[e], (n, -1))
            ok = np.all(np.isfinite(col), axis=1) & np.all(np.isfinite(d[i]), axis=1)
            num += np.einsum("tj,tj->j", d[i][ok], col[ok])
            den += np.einsum("tj,tj->j", col[ok], col[ok])
    if np.any(den <= 0) or np.any(num == 0):
        return None
    return list(num / den)


def _value(fit: FitResult, prm, experiment: str) -> float:
    est = fit.parameters.get(f"{prm.name}[{experiment}]") or fit.parameters.get(prm.name)
    return prm.value if est is None else est.value


def start_is_sound(request: FitRequest, fit: FitResult, model: Model) -> bool:
    """Whether `model` at its initial values simulates the records about as well as the fit it extends.

    Parameters
    ----------
    request : FitRequest
        The fit's request (its experiments and options).
    fit : FitResult
        The fit the refit extends (its initial states, per-experiment parameters and RMSE per output).
    model : Model
        The augmented model with its start values.

    Returns
    -------
    bool
        False when the simulation fails, is not finite, or its RMSE on some output exceeds
        `START_MAX_RMSE_RATIO` times the fit's; True otherwise (and when the fit has no RMSE to compare).
    """
    from greyfit.solvers.errors import FitError
    from greyfit.solvers.simulation.simulate import validation_metrics
    values = {p.name: p.value for p in model.parameters}
    values.update({label: est.value for label, est in fit.parameters.items() if est.experiment is not None})
    try:
        res = validation_metrics(model, values, request.experiments, request.options, fit.initial_states)
    except (FitError, RuntimeError, ValueError, FloatingPointError):
        return False
    for name, rmse in res.rmse.items():
        ref = fit.metrics.rmse.get(name)
        if rmse is None or not np.isfinite(rmse):
            return False
        if ref is not None and np.isfinite(ref) and rmse > START_MAX_RMSE_RATIO * max(ref, 1e-300):
            return False
    return True
