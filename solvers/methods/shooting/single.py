"""Single shooting: one simulation per record from the initial states (mapaccum), residual y_sim − y."""
from __future__ import annotations

import casadi as ca
import numpy as np

from greyfit.solvers.methods.shooting import structured as shooting_structured
from greyfit.solvers.methods.shooting.model import OutputErrorModel, x0_reader
from greyfit.solvers.nlp.problem import (
    LeastSquaresProblem,
    parameter_constraints,
    theta_bounds,
)


def build_single_shooting(oem: OutputErrorModel) -> LeastSquaresProblem:
    """Build the single-shooting NLP: decision vector [θ, free initial states] (scaled), residual y_sim − y.

    Parameters
    ----------
    oem : OutputErrorModel
        The output-error model (compiled model, data, layout, options, free initial states).

    Returns
    -------
    LeastSquaresProblem
        In the structured form (its own compiled solver) where `structured.supports` it, else over a
        CasADi graph of the mapped simulation with the parameter constraints.
    """
    nfree = sum(len(f) for f in oem.free_x0)
    lo, hi = theta_bounds(oem.layout)
    offsets = np.cumsum([0] + [len(f) for f in oem.free_x0])

    def initial_guess(theta_phys: np.ndarray) -> np.ndarray:
        x0 = [oem.x0_guess(e)[f] / oem.xscale[f] for e, f in enumerate(oem.free_x0)]
        return np.concatenate([theta_phys / oem.layout.scale, *x0]) if nfree else theta_phys / oem.layout.scale

    common = dict(lbw=np.concatenate([lo, -np.inf * np.ones(nfree)]), ubw=np.concatenate([hi, np.inf * np.ones(nfree)]),
                  n_theta=oem.layout.size, initial_guess=initial_guess,
                  x0_of=x0_reader(oem, oem.layout.size, lambda e: int(offsets[e])),
                  extra_labels=oem.x0_labels())
    if shooting_structured.supports(oem, single=True):
        n_par = shooting_structured.constraint_count(oem)
        problem = LeastSquaresProblem(
            w=ca.MX.sym("w", oem.layout.size + nfree), residual_builder=lambda: None,
            g=ca.MX.sym("g", n_par), lbg=shooting_structured.constraint_lower(oem),
            ubg=shooting_structured.constraint_upper(oem), **common)
        return shooting_structured.attach_solver(oem, problem, single=True)
    theta, x0_free, r = oem.single_shooting_residual()
    g, lbg, ubg = parameter_constraints(oem.cm, oem.layout, theta)
    return LeastSquaresProblem(
        w=ca.vertcat(theta, x0_free), residual_builder=lambda: r, g=ca.vertcat(*g),
        lbg=np.concatenate(lbg) if lbg else np.zeros(0), ubg=np.concatenate(ubg) if ubg else np.zeros(0),
        **common)
