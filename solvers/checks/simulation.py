"""The integrator step on numpy columns for the checks that simulate outside the solve.

The substep choice simulates at the initial guess and the errors-in-variables check at the
estimate. A `mapaccum` built per call and evaluated by CasADi's interpreter costs 0.3 s on a
40 000-sample record; the step's compiled sample loop (`solvers.dynamics.columns`), kept on the
compiled model, costs a few milliseconds and is built once per model structure.
"""
from __future__ import annotations

from greyfit.schemas.fit import FitOptions
from greyfit.solvers.dynamics.columns import Columns
from greyfit.solvers.dynamics.integration import make_step
from greyfit.solvers.model.compiler import CompiledModel


def numeric_step(cm: CompiledModel, options: FitOptions, evaluations: float = 0.0) -> Columns:
    """step(x, u0, u1, p, t0, dt) -> x(t0 + dt) on numpy columns, cached per model and integrator settings.

    Call it with ``accumulate=True`` to simulate: the states after each of `n` intervals, (nx, n).

    Parameters
    ----------
    cm : CompiledModel
        The compiled model (the cache lives on it).
    options : FitOptions
        Fit options; `integrator`, `substeps` and `input_interpolation` shape the step.
    evaluations : float, optional
        Expected number of step evaluations per use (decides whether compiling now repays itself).

    Returns
    -------
    Columns
        The step over the columns of numpy arrays (compiled C where available, else CasADi's map).
    """
    key = ("step_columns", options.integrator, options.substeps, options.input_interpolation)
    return cm.derive(key, lambda: Columns(make_step(cm, options), evaluations))
