"""The pieces `fit_model` hands to the trust checks: excitation at the start, row keys for the
robust covariance, active constraints, state sizes. Kept here so `fit_model` stays an outline."""
from __future__ import annotations

import casadi as ca
import numpy as np

from greyfit.schemas.fit import FitOptions, FitWarning
from greyfit.solvers.checks.excitation import information_warnings, input_warnings, step_size_warning
from greyfit.solvers.data.experiments import ExperimentData
from greyfit.solvers.dynamics.integration import integrator_of
from greyfit.solvers.methods.equation_error import EquationErrorProblem
from greyfit.solvers.methods.method_choice import eigenvalues, state_jacobian_columns
from greyfit.solvers.methods.node_initialisation import DIVERGED
from greyfit.solvers.methods.shooting import OutputErrorModel, sensitivity_jacobian
from greyfit.solvers.model.compiler import CompiledModel
from greyfit.solvers.model.parameters import ParameterLayout
from greyfit.solvers.timing import stage

ACTIVE_TOLERANCE = 1e-6


def pre_fit_warnings(cm: CompiledModel, data: list[ExperimentData], layout: ParameterLayout,
                     options: FitOptions, problem, eep: EquationErrorProblem | None,
                     oem: OutputErrorModel | None) -> list[FitWarning]:
    """Excitation of the parameters at the initial guess and of every input (before solving).

    Parameters
    ----------
    cm : CompiledModel
        The compiled model.
    data : list of ExperimentData
        The prepared experiments.
    layout : ParameterLayout
        Layout of the free parameters (their initial values are the guess).
    options : FitOptions
        Fit options (the input interpolation).
    problem : LeastSquaresProblem
        The fit's NLP; its Jacobian at the guess is used for equation error.
    eep : EquationErrorProblem or None
        The equation-error problem, when the method is equation error.
    oem : OutputErrorModel or None
        The output-error model otherwise; its sensitivities at the guess are used (NaN when the
        simulation runs away), and a simulation failure there is not recorded.

    Returns
    -------
    list of FitWarning
        As `information_warnings` followed by `input_warnings`.

    Raises
    ------
    DataError
        As `information_warnings`.
    ValueError
        When neither `eep` nor `oem` is given (a caller's error).
    """
    theta_s = layout.initial / layout.scale
    if eep is not None:
        jac, _ = problem.evaluate_jacobian(problem.initial_guess(layout.initial))
        gram = jac.T @ jac
        labels = list(layout.labels)
    elif oem is None:   # each batch method builds one of the two (solvers/methods/batch.py)
        raise ValueError("pre_fit_warnings needs the equation-error problem or the output-error model")
    else:
        failures = len(oem.simulation_failures)
        if problem.start_gram is not None:   # the solve's own first pass, done here for it
            w0 = np.clip(problem.initial_guess(layout.initial), problem.lbw, problem.ubw)   # as run_ipopt
            with stage("solve"):   # the fit's timings count the pass where it serves
                gram = problem.start_gram(w0)
        else:
            x0s = [dict(zip(cm.states, oem.x0_guess(e))) for e in range(len(data))]
            jac, _, _ = sensitivity_jacobian(oem, theta_s, x0s)
            with np.errstate(over="ignore", invalid="ignore"):   # an overflow is judged as not finite
                gram = jac.T @ jac if np.all(np.isfinite(jac)) else np.full((jac.shape[1],) * 2, np.nan)
        if _runs_away(oem, layout):
            gram = np.full_like(gram, np.nan)   # sensitivities of a run-away simulation say nothing
        del oem.simulation_failures[failures:]   # a failure at the guess is reported as a warning
        labels = list(layout.labels) + oem.x0_labels()
    inputs = {name: [d.u[k] for d in data] for k, name in enumerate(cm.inputs)}
    # a difference equation reads u[k] only, and equation error reads the inputs at the samples (through
    # its derivative filter): nothing is interpolated between samples, so no interpolation warning
    interpolation = "zoh" if cm.model.discrete is not None or eep is not None else options.input_interpolation
    return information_warnings(gram, labels) + input_warnings(inputs, interpolation, input_parameters(cm, layout))


def _runs_away(oem: OutputErrorModel, layout: ParameterLayout) -> bool:
    """The simulation at the initial guess leaves every sane range (|x| > 1e12) or fails."""
    sims = oem.simulate(layout.initial, [oem.x0_guess(e) for e in range(len(oem.data))])
    return any(not np.all(np.isfinite(s)) or np.max(np.abs(s), initial=0.0) > DIVERGED for s, _ in sims)


def input_parameters(cm: CompiledModel, layout: ParameterLayout) -> dict[str, list[str]]:
    """Per input, the free parameters that act on it in some equation (∂²f/∂u∂p ≠ 0).

    Parameters
    ----------
    cm : CompiledModel
        The compiled model (the structural part is computed once per model).
    layout : ParameterLayout
        Layout of the free parameters.

    Returns
    -------
    dict of str to list of str
        Per input name, the sorted names of the free parameters acting on it.
    """
    acting = cm.derive(("input_parameters",), lambda: _parameters_on_inputs(cm))
    free = set(layout.base_names)
    return {name: sorted(acting[name] & free) for name in cm.inputs}


def _parameters_on_inputs(cm: CompiledModel) -> dict[str, set[str]]:
    x, u, p, t = ca.SX.sym("x", cm.nx), ca.SX.sym("u", cm.nu), ca.SX.sym("p", cm.np), ca.SX.sym("t")
    f = cm.rhs(x, u, p, t)
    out = {}
    for k, name in enumerate(cm.inputs):
        _, cols = ca.jacobian(ca.jacobian(f, u[k]), p).sparsity().get_triplet()
        out[name] = {cm.parameters[j] for j in cols}
    return out


def fastest_rate_warning(cm: CompiledModel, data: list[ExperimentData], layout: ParameterLayout,
                         theta_s: np.ndarray, states: list[np.ndarray], options: FitOptions) -> list[FitWarning]:
    """Largest |eigenvalue| of ∂f/∂x along the fitted trajectory against the RK4 step.

    Parameters
    ----------
    cm : CompiledModel
        The compiled model.
    data : list of ExperimentData
        The prepared experiments.
    layout : ParameterLayout
        Layout of the free parameters.
    theta_s : numpy.ndarray
        Fitted scaled parameters, shape (n_theta,).
    states : list of numpy.ndarray
        Fitted state trajectory of each experiment, shape (nx, N).
    options : FitOptions
        Fit options (integrator and substeps).

    Returns
    -------
    list of FitWarning
        As `step_size_warning`; empty for an adaptive integrator or a discrete-time model.
    """
    if not integrator_of(options).fixed_step or cm.model.discrete is not None:   # no integration step to judge
        return []
    rate, dt = fastest_rate(cm, data, layout, theta_s, states)
    return step_size_warning(rate, dt, options.substeps, options.integrator)


def fastest_rate(cm: CompiledModel, data: list[ExperimentData], layout: ParameterLayout,
                 theta_s: np.ndarray, states: list[np.ndarray]) -> tuple[float, float]:
    """(largest |eigenvalue| of ∂f/∂x at up to 20 points of each trajectory, smallest median step).

    Parameters
    ----------
    cm, data, layout, theta_s, states
        As in `fastest_rate_warning`.

    Returns
    -------
    rate : float
        Largest |eigenvalue| of ∂f/∂x at the finite points, in 1/time unit (0 when none is finite).
    dt : float
        Smallest median sample step over the experiments.
    """
    jac_fn = state_jacobian_columns(cm)
    rate, dt = 0.0, np.inf
    for e, d in enumerate(data):
        pe = np.asarray(layout.full(e, theta_s), dtype=float).ravel()
        ks = np.linspace(0, d.n - 1, min(d.n, 20)).astype(int)
        ks = ks[np.all(np.isfinite(states[e][:, ks]), axis=0)]
        if ks.size:
            a, = jac_fn(states[e][:, ks], d.u[:, ks], pe, d.t[None, ks], n=ks.size)
            blocks = a.reshape(cm.nx, ks.size, cm.nx).transpose(1, 0, 2)
            blocks = blocks[np.all(np.isfinite(blocks), axis=(1, 2))]
            if blocks.size:
                rate = max(rate, float(np.max(np.abs(eigenvalues(blocks)))))
        dt = min(dt, float(np.median(np.diff(d.t))))
    return rate, dt


def row_keys(data: list[ExperimentData], eep: EquationErrorProblem | None,
             cm: CompiledModel) -> tuple[np.ndarray, np.ndarray]:
    """(sample key, experiment) of every residual row, in the order of the covariance Jacobian.

    Parameters
    ----------
    data : list of ExperimentData
        The prepared experiments.
    eep : EquationErrorProblem or None
        The equation-error problem (rows per used sample and equation), or None for output error
        (rows per measured output sample, sample-major).
    cm : CompiledModel
        The compiled model.

    Returns
    -------
    sample_keys : numpy.ndarray
        Per row, its sample index offset by the samples of the preceding experiments.
    experiment_keys : numpy.ndarray
        Per row, the index of its experiment.
    """
    keys, exps, base = [], [], 0
    for e, d in enumerate(data):
        if eep is not None:
            samples = np.repeat(eep.per_experiment[e].rows, len(eep.equations))
        else:
            samples = np.nonzero(d.mask.T)[0]   # sample-major, measured entries only
        keys.append(base + samples)
        exps.append(np.full(samples.size, e))
        base += d.n
    return np.concatenate(keys), np.concatenate(exps)


def active_constraints(cm: CompiledModel, layout: ParameterLayout, theta_s: np.ndarray) -> list[str]:
    """User constraints (inequalities) that hold with equality at the solution.

    Parameters
    ----------
    cm : CompiledModel
        The compiled model with its constraint function.
    layout : ParameterLayout
        Layout of the free parameters.
    theta_s : numpy.ndarray
        Fitted scaled parameters, shape (n_theta,).

    Returns
    -------
    list of str
        The texts of the inequality constraints with |g| ≤ `ACTIVE_TOLERANCE` × max(1, max |p|) in
        some experiment, in declaration order.
    """
    if cm.constraint is None:
        return []
    texts = list(cm.model.constraints)
    active = set()
    for e in range(len(layout.matrix)):
        g = np.array(cm.constraint(layout.full(e, theta_s))).ravel()
        tolerance = ACTIVE_TOLERANCE * max(1.0, _size(cm, layout, e, theta_s))
        for i, value in enumerate(g):
            if not cm.constraint_equality[i] and abs(value) <= tolerance:
                active.add(i)
    return [texts[i] for i in sorted(active)]


def _size(cm: CompiledModel, layout: ParameterLayout, e: int, theta_s: np.ndarray) -> float:
    return float(np.max(np.abs(np.asarray(layout.full(e, theta_s), dtype=float)), initial=1.0))


def state_peaks(oem: OutputErrorModel, states: list[np.ndarray], theta_guess: np.ndarray):
    """(max |x| per state at the solution, the same for a simulation at the initial guess).

    Parameters
    ----------
    oem : OutputErrorModel
        The output-error model (a simulation failure at the guess is not recorded).
    states : list of numpy.ndarray
        Fitted state trajectory of each experiment, shape (nx, N).
    theta_guess : numpy.ndarray
        Initial physical parameters.

    Returns
    -------
    fitted : numpy.ndarray
        Largest |x| per state over the fitted trajectories, shape (nx,).
    guess : numpy.ndarray
        The same at the initial guess, at least the state scale; inf for a state whose simulation
        there is not finite.
    """
    fitted = np.max(np.abs(np.hstack(states)), axis=1)
    failures = len(oem.simulation_failures)
    sims = oem.simulate(theta_guess, [oem.x0_guess(e) for e in range(len(oem.data))])
    del oem.simulation_failures[failures:]
    peaks = np.abs(np.hstack([s for s, _ in sims]))
    guess = np.where(np.isfinite(peaks).all(axis=1), np.max(np.where(np.isfinite(peaks), peaks, 0), axis=1),
                     np.inf)   # a diverged simulation at the guess gives no reference
    return fitted, np.maximum(guess, oem.xscale)
