"""Starts of a fit and the solve over them: the user's guess first, then draws inside the bounds."""
from __future__ import annotations

import time

import numpy as np

from greyfit.schemas.fit import FitOptions
from greyfit.solvers.methods.shooting_curvature import make_solver
from greyfit.solvers.model.parameters import ParameterLayout
from greyfit.solvers.nlp.problem import LeastSquaresProblem
from greyfit.solvers.nlp.solver import NlpOutcome, solve_linear_least_squares


def draw_starts(layout: ParameterLayout, n: int, seed: int) -> list[np.ndarray]:
    """The user's guess first, then n-1 draws inside the bounds (log-uniform over decades).

    Parameters
    ----------
    layout : the parameter layout (bounds, initial values, scales).
    n : number of starts, the guess included.
    seed : seed of the random draws (the same seed gives the same starts).

    Returns
    -------
    list of physical parameter vectors.
    """
    starts = [layout.initial.copy()]
    rng = np.random.default_rng(seed)
    for _ in range(n - 1):
        theta = np.empty(layout.size)
        for i in range(layout.size):
            lo, hi, v = layout.lower[i], layout.upper[i], layout.initial[i]
            lo = lo if np.isfinite(lo) else v - 0.5 * layout.scale[i]
            hi = hi if np.isfinite(hi) else v + 0.5 * layout.scale[i]
            if lo > 0 and hi / lo > 10:
                theta[i] = np.exp(rng.uniform(np.log(lo), np.log(hi)))
            else:
                theta[i] = rng.uniform(lo, hi)
        starts.append(theta)
    return starts


def solve_from_starts(problem: LeastSquaresProblem, options: FitOptions, starts: list[np.ndarray],
                      linear: bool, cpu0: float | None = None) -> tuple[NlpOutcome, int, bool | None]:
    """Solve from each start and keep the best (converged first, then the lower cost).

    Parameters
    ----------
    problem : the method's least-squares NLP.
    options : the request's options (max_cpu_time bounds the whole fit, preparation included).
    starts : physical parameter vectors, the user's guess first.
    linear : the residual is affine in θ: try the closed form first.
    cpu0 : the process time the fit began at.

    Returns
    -------
    (best outcome, number of starts used, whether compiled C evaluated the model or None).
    """
    if linear:
        outcome = solve_linear_least_squares(problem, options)
        if outcome is not None:
            return outcome, 1, None
    solver = make_solver(problem, options)   # multiple shooting: with its gaps' curvature
    best: NlpOutcome | None = None
    used = 0
    cpu0 = time.process_time() if cpu0 is None else cpu0
    solving = time.process_time()
    for theta0 in starts:
        now = time.process_time()
        # max_cpu_time bounds the whole fit, not each start: another start is begun only if one
        # more, at the cost of those so far, still ends inside it
        if best is not None and now - cpu0 + (now - solving) / used > options.max_cpu_time:
            break
        out = solver.solve(problem.initial_guess(theta0))
        used += 1
        if best is None or (out.success, -out.cost) > (best.success, -best.cost):
            best = out
    assert best is not None   # starts always holds the user's guess
    return best, used, solver.compiled
