"""D-, A- and E-optimal inputs: the signal that makes the parameters' predicted covariance smallest.

The NLP is z (the signal's coefficients) -> criterion(F(z)), with F the Fisher information of
`simulation.information_function`, averaged over parameter draws when the design is to be robust
to the estimates' uncertainty. Ipopt solves it from a few seeded starts (and the baseline's input);
the best is kept.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import casadi as ca
import numpy as np

from greyfit.schemas.design import DesignRequest
from greyfit.solvers.design.criteria import criterion_function, criterion_value, predicted_stderrs
from greyfit.solvers.design.setup import Candidate, DesignSetup
from greyfit.solvers.design.simulation import information_function
from greyfit.solvers.errors import DataError

# a parameter of interest whose relative information is below this share of the largest is not
# seen by the measured outputs under the input tried: the design cannot help it
UNSEEN = 1e-12
# relative information whose smallest eigenvalue is below this share of the largest: a combination of
# parameters the outputs do not determine (a local, numerical statement of structural non-identifiability)
SINGULAR = 1e-10


@dataclass
class Solved:
    """The kept start's design."""

    z: np.ndarray
    objective: float
    status: str
    iterations: int


def information(model: Candidate, x0: np.ndarray, U: np.ndarray, time: np.ndarray, substeps: int,
                p: Optional[np.ndarray] = None) -> np.ndarray:
    """The Fisher information of the model's free parameters for input U on the sample times.

    Parameters
    ----------
    model : Candidate
        The model and its parameter values.
    x0 : ndarray
        Initial state.
    U : ndarray
        Inputs × samples, held between samples.
    time : ndarray
        Sample times.
    substeps : int
        RK4 steps per sample.
    p : ndarray, optional
        Parameter vector (default: the model's values).

    Returns
    -------
    ndarray
        len(free) × len(free).
    """
    n = len(time)
    fun = information_function(model.cm, n, substeps, model.measured.rows, model.free)
    F = fun(x0, U, model.p if p is None else p, time.reshape(1, -1), np.diff(time).reshape(1, -1),
            1.0 / model.measured.sigma ** 2)
    return np.asarray(F, dtype=float)


def parameter_draws(setup: DesignSetup, request: DesignRequest, rng: np.random.Generator) -> list[np.ndarray]:
    """The nominal parameters, and `robust_draws` draws from the covariance (clipped to the bounds).

    Parameters
    ----------
    setup : DesignSetup
        The model and the covariance.
    request : DesignRequest
        `robust_draws`.
    rng : numpy.random.Generator
        Seeded.

    Returns
    -------
    list of numpy.ndarray
        Full parameter vectors, the nominal first.
    """
    model = setup.model
    draws = [model.p]
    if request.robust_draws and setup.covariance is not None:
        free = list(model.free)
        chol = np.linalg.cholesky(setup.covariance + 1e-14 * np.eye(len(free)) * np.trace(setup.covariance))
        for _ in range(request.robust_draws):
            p = model.p.copy()
            p[free] = np.clip(model.p[free] + chol @ rng.standard_normal(len(free)), model.lower, model.upper)
            draws.append(p)
    return draws


def _scale(model: Candidate) -> np.ndarray:
    values = np.abs(model.p[list(model.free)])
    return np.where(values > 0, values, 1.0)


def check_seen(setup: DesignSetup, U: np.ndarray, substeps: int) -> None:
    """Refuse a design for a parameter the measured outputs do not depend on (under a rich input).

    Parameters
    ----------
    setup : DesignSetup
        The laid-out design.
    U : numpy.ndarray
        A rich input inside the limits.
    substeps : int
        RK4 steps per sample.
    """
    scale = _scale(setup.model)
    F = information(setup.model, setup.x0, U, setup.time, substeps)
    rel = np.diag(F) * scale ** 2
    top = float(np.max(rel)) if rel.size else 0.0
    names = setup.model.free_names
    for i in setup.interest:
        if not np.isfinite(rel[i]) or rel[i] <= UNSEEN * max(top, 1e-300):
            raise DataError(f"the measured outputs do not depend on parameter {names[i]!r} under the input's "
                            "limits (its output sensitivity vanishes): measure another output, or leave it out",
                            "parameters_of_interest")


def _nlp(setup: DesignSetup, request: DesignRequest,
         draws: list[np.ndarray]) -> tuple[ca.Function, np.ndarray, np.ndarray]:
    model, signal, time = setup.model, setup.signal, setup.time
    z = ca.MX.sym("z", signal.nz)
    U = signal.inputs(z)
    fun = information_function(model.cm, len(time), request.options.substeps, model.measured.rows, model.free)
    crit = criterion_function(request.criterion, len(model.free), setup.interest)
    t, dt, w = ca.DM(time.reshape(1, -1)), ca.DM(np.diff(time).reshape(1, -1)), ca.DM(1.0 / model.measured.sigma ** 2)
    scale = ca.DM(_scale(model))
    f = sum(crit(fun(ca.DM(setup.x0), U, ca.DM(p), t, dt, w), scale) for p in draws) / len(draws)
    g, lbg, ubg = signal.constraints(z)
    opts = {"ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes",
            "ipopt.max_iter": request.options.max_iterations, "ipopt.tol": 1e-7,
            "ipopt.hessian_approximation": "limited-memory"}
    solver = ca.nlpsol("design", "ipopt", {"x": z, "f": f, "g": g}, opts)
    return solver, lbg, ubg


def solve_information_design(setup: DesignSetup, request: DesignRequest, starts: list[np.ndarray],
                             rng: np.random.Generator) -> Solved:
    """Minimise the criterion from each start; the best converged design (exact criterion) is kept.

    Parameters
    ----------
    setup : DesignSetup
        The laid-out design.
    request : DesignRequest
        Criterion, options, robust draws.
    starts : list of ndarray
        Starting z's.
    rng : numpy.random.Generator
        For the parameter draws.

    Returns
    -------
    Solved
    """
    draws = parameter_draws(setup, request, rng)
    solver, lbg, ubg = _nlp(setup, request, draws)
    signal, best = setup.signal, None
    for z0 in starts:
        sol = solver(x0=z0, lbx=signal.lbz, ubx=signal.ubz, lbg=lbg, ubg=ubg)
        z = np.clip(np.asarray(sol["x"], dtype=float).reshape(-1), signal.lbz, signal.ubz)
        value = exact_criterion(setup, request, signal.inputs(z))
        stats = solver.stats()
        if best is None or value < best.objective:
            best = Solved(z, value, str(stats.get("return_status", "")), int(stats.get("iter_count", 0)))
    assert best is not None   # starts is never empty
    return best


def exact_criterion(setup: DesignSetup, request: DesignRequest, U: np.ndarray,
                    time: Optional[np.ndarray] = None, x0: Optional[np.ndarray] = None) -> float:
    """The criterion of input U at the nominal parameters (E: the largest eigenvalue itself).

    Parameters
    ----------
    setup : DesignSetup
        The laid-out design.
    request : DesignRequest
        The criterion.
    U : numpy.ndarray
        Inputs × samples.
    time : numpy.ndarray, optional
        Sample times (default the design's).
    x0 : numpy.ndarray, optional
        Initial state (default the design's).

    Returns
    -------
    float
        The criterion.
    """
    F = information(setup.model, setup.x0 if x0 is None else x0, U, setup.time if time is None else time,
                    request.options.substeps)
    return criterion_value(request.criterion, F, _scale(setup.model), setup.interest)


def check_identifiable(setup: DesignSetup, U: np.ndarray, substeps: int) -> None:
    """Refuse a design whose information stays singular: the outputs fix only a combination of parameters.

    Parameters
    ----------
    setup : DesignSetup
        The laid-out design.
    U : ndarray
        The designed input (the best the criterion found: if it cannot separate them, none can locally).
    substeps : int
        RK4 steps per sample.
    """
    scale = _scale(setup.model)
    F = information(setup.model, setup.x0, U, setup.time, substeps)
    rel = np.diag(scale) @ F @ np.diag(scale)
    values, vectors = np.linalg.eigh(0.5 * (rel + rel.T))
    if values[-1] > 0 and values[0] > SINGULAR * values[-1]:
        return
    names = setup.model.free_names
    weights = np.abs(vectors[:, 0])
    involved = [names[i] for i in np.argsort(-weights) if weights[i] > 0.1]
    raise DataError(f"the measured outputs determine only a combination of {', '.join(involved)} under any input "
                    "the design found: fix one of them, or measure another output", "model.parameters")


def stderrs(setup: DesignSetup, U: np.ndarray, time: np.ndarray, x0: np.ndarray, substeps: int) -> Optional[np.ndarray]:
    """Predicted standard errors of the free parameters for input U.

    Parameters
    ----------
    setup : DesignSetup
        The laid-out design.
    U : numpy.ndarray
        Inputs × samples.
    time : numpy.ndarray
        Sample times.
    x0 : numpy.ndarray
        Initial state.
    substeps : int
        RK4 steps per sample.

    Returns
    -------
    numpy.ndarray or None
        One per free parameter; None where the information is singular.
    """
    return predicted_stderrs(information(setup.model, x0, U, time, substeps))
