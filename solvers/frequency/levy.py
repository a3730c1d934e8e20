"""Levy's linearised fit and Sanathanan-Koerner (SK) reweighting: a start that needs no guess.

Levy minimises ``Σ |D(jω_i) G_i - N(jω_i)|²``: the error multiplied by the denominator, which is
affine in the coefficients (convex when the coefficients are affine in the parameters, as in the
course notes on parameter estimation from frequency data). Its implicit weight ``|D(jω)|²`` grows
like ``ω^(2n)``, so on noisy data the high frequencies
dominate and the low-frequency poles come out biased. SK iteration k divides by ``|D_(k-1)(jω)|``,
which removes that weight at convergence (the fixed point fits ``(G - N/D)`` with ``D/D_prev -> 1``).
"""
from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from greyfit.schemas.fit import FitOptions
from greyfit.solvers.frequency.data import FrequencySet
from greyfit.solvers.frequency.polynomials import ClosedLoop
from greyfit.solvers.frequency.response import evaluate_polynomial
from greyfit.solvers.model.parameters import ParameterLayout
from greyfit.solvers.nlp.problem import LeastSquaresProblem
from greyfit.solvers.nlp.solver import LeastSquaresSolver, solve_linear_least_squares

CPU_LIMIT_STATUS = "Maximum_CpuTime_Exceeded"   # Ipopt's, at options.max_cpu_time


@dataclass
class LevyOutcome:
    theta: np.ndarray          # physical parameters (layout order)
    iterations: int            # SK reweightings done after Levy
    status: str


def _levy_residual(theta, loops: list[ClosedLoop], sets: list[FrequencySet], layout: ParameterLayout,
                   weights: list[np.ndarray]):
    rows = []
    for e, (loop, s) in enumerate(zip(loops, sets)):
        p = layout.full(e, theta)
        nr, ni = evaluate_polynomial(loop.num_fn(p), s.omega)
        dr, di = evaluate_polynomial(loop.den_fn(p), s.omega)
        gr, gi = s.response.real, s.response.imag
        er, ei = dr * gr - di * gi - nr, dr * gi + di * gr - ni
        rows.append(ca.vertcat(er * weights[e], ei * weights[e]))
    return ca.vertcat(*rows)


def _solve(theta, residual, layout, constrained: bool, g, lbg, ubg, options: FitOptions):
    lbw = layout.lower / layout.scale if constrained else np.full(layout.size, -np.inf)
    ubw = layout.upper / layout.scale if constrained else np.full(layout.size, np.inf)
    if not constrained:
        g, lbg, ubg = ca.MX(0, 1), np.zeros(0), np.zeros(0)
    problem = LeastSquaresProblem(w=theta, residual_builder=lambda: residual, g=g, lbg=lbg, ubg=ubg,
                                  lbw=lbw, ubw=ubw, n_theta=layout.size,
                                  initial_guess=lambda t: np.asarray(t, float) / layout.scale,
                                  x0_of=lambda w: [])
    affine = not ca.depends_on(ca.jacobian(residual, theta), theta)
    outcome = solve_linear_least_squares(problem, options) if affine else None
    if outcome is None:
        outcome = LeastSquaresSolver(problem, options).solve(problem.initial_guess(layout.initial))
    return outcome.w, outcome.status


def levy_fit(loops: list[ClosedLoop], sets: list[FrequencySet], layout: ParameterLayout, *,
             iterations: int = 0, data_weights: list[np.ndarray] | None = None, constrained: bool = True,
             constraint=None, options: FitOptions | None = None) -> LevyOutcome:
    """Levy's fit, then `iterations` SK reweightings (each also weighted by `data_weights`).

    Parameters
    ----------
    loops : list of ClosedLoop
        The measured loop of each data set, in the order of `sets`.
    sets : list of FrequencySet
        The measured data sets.
    layout : ParameterLayout
        The free parameters (scales, bounds, guesses: the common scale of Levy proper is taken there).
    iterations : int
        Most SK reweightings; they stop early when the relative step is below 1e-10.
    data_weights : list of numpy.ndarray or None
        Per-set (N_e,) weights multiplied into the SK weights; None: 1.
    constrained : bool
        Keep the parameter bounds and `constraint`; False gives the plain (unconstrained) Levy
        estimate of the textbook.
    constraint : tuple or None
        (Function θ -> g, lbg, ubg), θ scaled; None: no constraint.
    options : FitOptions or None
        Solver options; None: 500 iterations, tolerance 1e-10.

    Returns
    -------
    LevyOutcome
        The physical estimate (layout order), the number of SK reweightings done and the last
        solver status, or CPU_LIMIT_STATUS where the CPU limit stopped any of the solves.
    """
    options = options or FitOptions(max_iter=500, tol=1e-10)
    theta = ca.MX.sym("theta", layout.size)
    if constraint is None:
        g, lbg, ubg = ca.MX(0, 1), np.zeros(0), np.zeros(0)
    else:
        g, lbg, ubg = constraint[0](theta), constraint[1], constraint[2]
    # one common scale for Levy proper: its minimiser does not change, the solver sees O(1) numbers
    w0 = []
    for loop, s in zip(loops, sets):
        p0 = layout.full(0, layout.initial / layout.scale)
        dr, di = evaluate_polynomial(np.array(loop.den_fn(p0)).ravel(), s.omega)
        w0.append(np.abs(s.response) * np.hypot(dr, di))
    common = 1.0 / max(float(np.max(np.concatenate(w0))), 1e-300)
    weights = [np.full(s.omega.size, common) for s in sets]
    w_s, status = _solve(theta, _levy_residual(theta, loops, sets, layout, weights), layout, constrained,
                         g, lbg, ubg, options)
    cut = status if status == CPU_LIMIT_STATUS else None
    done = 0
    for _ in range(iterations):
        weights = []
        for e, (loop, s) in enumerate(zip(loops, sets)):
            dr, di = evaluate_polynomial(np.array(loop.den_fn(layout.full(e, w_s))).ravel(), s.omega)
            dw = 1.0 if data_weights is None else data_weights[e]
            weights.append(dw / np.maximum(np.hypot(dr, di), 1e-300))
        new_w, status = _solve(theta, _levy_residual(theta, loops, sets, layout, weights), layout,
                               constrained, g, lbg, ubg, options)
        cut = cut or (status if status == CPU_LIMIT_STATUS else None)
        done += 1
        step = np.max(np.abs(new_w - w_s) / np.maximum(np.abs(w_s), 1e-12))
        w_s = new_w
        if step < 1e-10:
            break
    return LevyOutcome(layout.physical(w_s), done, cut or status)
