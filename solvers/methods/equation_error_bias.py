"""Errors in variables: is an equation-error estimate biased by noise in its regressors?

Equation error regresses the measured derivative (or next sample) on measured states. Noise in
those states is noise in the regressors, and least squares is then biased, however long the
record (Robust parameter estimation by noise reduction, Aoki and Kawata: on its second-order
example 20000/(s² + 2s + 10000) the damping ap1 comes out +155 % at a noise power of 1e-5, and
the fit looked `good`). The check is an instrumental-variable (IV) re-estimate: the instruments are
the regressors (the residual's Jacobian) evaluated on the model's own simulation at the LS
estimate, which correlate with the measured signals but not with their noise. (Regressors lagged
by a few samples were tried first: with a white input the lagged input columns are weak
instruments and the check lost its power.) Without errors in variables both estimates agree
within the standard error of their difference; a difference of more than `Z_LIMIT` standard errors
and more than `RELATIVE_LIMIT` of the value says the regressors are noisy (or the model is wrong
in a way that makes the equation error correlated over time) — `errors_in_variables_bias`, with
the IV values, and the cure: a prefilter (options.prefilter), output error, or the IV values.

The standard error of the difference is a Newey-West (HAC) one: the equation error of noisy data
is a moving average of the noise, so the contributions are correlated over a few samples.
"""
from __future__ import annotations

import numpy as np

from greyfit.schemas.fit import FitWarning
from greyfit.solvers.checks.simulation import numeric_step
from greyfit.solvers.inference.robust_covariance import bartlett_sum
from greyfit.solvers.methods.equation_error import EquationErrorProblem
from greyfit.solvers.model.parameters import ParameterLayout

CODE = "errors_in_variables_bias"     # in quality.SUSPECT_CODES
Z_LIMIT = 4.0                          # IV − LS difference in its standard errors ...
RELATIVE_LIMIT = 0.02                  # ... and relative to the estimate
IV_ITERATIONS = 8
DIVERGED = 1e3                         # simulated states this many times the measured ones: no instruments
MIN_ROWS_PER_PARAMETER = 20


def hac_bandwidth(eep: EquationErrorProblem, discrete: bool, derivative_window: int) -> int:
    """Samples over which one equation row's noise reaches: the delay states, or the derivative's window.

    Parameters
    ----------
    eep : EquationErrorProblem
        The equation-error problem (its first experiment gives the number of states).
    discrete : bool
        True for a discrete-time model (the number of states sets the reach).
    derivative_window : int
        Window of the smoothing differentiator in samples (continuous time).

    Returns
    -------
    int
        HAC bandwidth in samples: number of states + 2 (discrete) or derivative window + 2.
    """
    nx = eep.per_experiment[0].x.shape[0]
    return nx + 2 if discrete else derivative_window + 2


def simulated_instruments(eep: EquationErrorProblem, cm, data, layout: ParameterLayout, w: np.ndarray,
                          options) -> np.ndarray | None:
    """The residual's Jacobian with the measured states replaced by the model's own simulation.

    The model at the least-squares estimate, driven by the measured input from the first row's
    measured state, gives states free of the measurement noise but close to the measured ones:
    instruments that correlate with the regressors and not with the noise in them (the refined
    instrumental variable idea). None when the simulation diverges.

    Parameters
    ----------
    eep : EquationErrorProblem
        The equation-error problem with its per-sample residual columns.
    cm : CompiledModel
        The compiled model.
    data : list of ExperimentData
        The experiments, in the order of `eep.per_experiment`.
    layout : ParameterLayout
        Maps the scaled θ to each experiment's parameters.
    w : numpy.ndarray
        The least-squares estimate of the scaled θ, shape (n θ,).
    options : FitOptions
        Integration options for the simulation.

    Returns
    -------
    numpy.ndarray or None
        Instruments, one row per residual row and one column per θ; None when the problem has no
        per-sample columns or the simulation diverges (non-finite or `DIVERGED` times the measured states).
    """
    if eep.sample is None:
        return None
    step = numeric_step(cm, options, sum(d.n for d in data))
    neq, blocks = len(eep.equations), []
    for e, (d, ed) in enumerate(zip(data, eep.per_experiment)):
        first, last = int(ed.rows[0]), int(ed.rows[-1])
        k = np.arange(first, last)
        p = np.asarray(layout.full(e, w), dtype=float)
        sim = step(ed.x[:, first], d.u[:, k], d.u[:, k + 1], p, d.t[k][None, :], (d.t[k + 1] - d.t[k])[None, :],
                   n=k.size, accumulate=True)[0] if k.size else np.zeros((cm.nx, 0))
        states = np.column_stack([ed.x[:, first], sim])[:, ed.rows - first]
        measured = np.abs(ed.x[:, ed.rows])
        size = np.max(measured, axis=1, keepdims=True, initial=0.0) if np.isfinite(measured).all() else \
            np.nanmax(measured, axis=1, keepdims=True)
        if not np.all(np.isfinite(states)) or np.any(np.abs(states) > DIVERGED * np.maximum(size, 1e-300)):
            return None
        n = ed.rows.size
        u = d.u if ed.u is None else ed.u        # the inputs the equations saw (kernel-averaged or recorded)
        _, jj = eep.sample(states, u[:, ed.rows], d.t[ed.rows][None, :], ed.dx[eep.equations][:, ed.rows],
                           p, eep.weights[eep.equations], n=n)
        jp = np.asarray(jj).reshape(neq, n, cm.np).transpose(1, 0, 2).reshape(n * neq, cm.np)
        blocks.append(jp @ layout.matrix[e])
    return np.vstack(blocks)


def _hac(moments: np.ndarray, bandwidth: int) -> np.ndarray:
    """Newey-West long-run covariance of the rows of `moments` (Bartlett weights)."""
    if bandwidth < moments.shape[0]:   # two cumulative sums instead of a product per lag
        return bartlett_sum(moments, bandwidth)
    s = moments.T @ moments
    for lag in range(1, bandwidth + 1):
        g = moments[lag:].T @ moments[:-lag]
        s += (1 - lag / (bandwidth + 1)) * (g + g.T)
    return s


def instrumental_estimate(eep: EquationErrorProblem, w: np.ndarray, z: np.ndarray, columns: np.ndarray,
                          bandwidth: int):
    """(IV estimate of the scaled θ, HAC covariance of IV − LS) from the LS solution `w` and the
    instruments `z` (one row per residual row); None when the instruments do not determine it.
    Only `columns` (parameters not on a bound) move.

    The covariance of the difference comes from its influence function A_IV⁻¹ z r_IV − A_LS⁻¹ j r_LS,
    so the noise common to both estimates cancels as it should.

    Parameters
    ----------
    eep : EquationErrorProblem
        The equation-error problem.
    w : numpy.ndarray
        The least-squares solution (scaled θ), shape (n θ,).
    z : numpy.ndarray
        Instruments, one row per residual row and one column per θ (`simulated_instruments`).
    columns : numpy.ndarray
        Boolean mask of the parameters not on a bound; only these move.
    bandwidth : int
        HAC bandwidth in samples per equation (`hac_bandwidth`).

    Returns
    -------
    tuple of (numpy.ndarray, numpy.ndarray) or None
        The IV estimate of the scaled θ (shape (n θ,)) and the HAC covariance of IV − LS over `columns`;
        None when the row count does not match the residual, there are fewer than
        `MIN_ROWS_PER_PARAMETER` rows per moving parameter, or the instruments are ill-conditioned.
    """
    z = z[:, columns]
    jac_ls, r_ls = eep.problem.evaluate_jacobian(w)
    if z.shape[0] != r_ls.size or z.shape[0] < MIN_ROWS_PER_PARAMETER * max(int(columns.sum()), 1):
        return None          # extra rows (a regularisation) or too few rows: no check
    theta = np.array(w, dtype=float)
    for _ in range(IV_ITERATIONS):
        jac, r = eep.problem.evaluate_jacobian(theta)
        a = z.T @ jac[:, columns]
        if not np.all(np.isfinite(a)) or np.linalg.cond(a) > 1e12:
            return None
        step = np.linalg.solve(a, z.T @ r)
        theta[columns] -= step
        if np.max(np.abs(step)) < 1e-10 * max(1.0, float(np.max(np.abs(theta)))):
            break
    jac, r = eep.problem.evaluate_jacobian(theta)
    j_ls = jac_ls[:, columns]
    # the influence functions row by row: (z r)ᵢ A⁻ᵀ, one small inverse instead of a solve per row
    psi_iv = (z * r[:, None]) @ np.linalg.inv(z.T @ jac[:, columns]).T
    psi_ls = (j_ls * r_ls[:, None]) @ np.linalg.inv(j_ls.T @ j_ls).T
    return theta, _hac(psi_iv - psi_ls, bandwidth=bandwidth * len(eep.equations))


def errors_in_variables_warnings(eep: EquationErrorProblem, layout: ParameterLayout, w: np.ndarray,
                                 z: np.ndarray, columns: np.ndarray, bandwidth: int) -> list[FitWarning]:
    """`errors_in_variables_bias` when the IV re-estimate moves a parameter significantly.

    Parameters
    ----------
    eep : EquationErrorProblem
        The equation-error problem that was solved.
    layout : ParameterLayout
        Its parameter layout (scales, labels).
    w : ndarray
        The least-squares solution (scaled θ first).
    z : ndarray
        The instruments (`simulated_instruments`).
    columns : ndarray of bool
        The parameters not on a bound.
    bandwidth : int
        The HAC bandwidth in samples (`hac_bandwidth`).

    Returns
    -------
    list of FitWarning
        One `errors_in_variables_bias` warning naming each parameter the re-estimate moved, or none.
    """
    iv = instrumental_estimate(eep, np.asarray(w, float)[:layout.size], z, columns, bandwidth)
    if iv is None:
        return []
    theta_iv, cov = iv
    ls, ivv = layout.physical(w[:layout.size]), layout.physical(theta_iv)
    se = np.full(layout.size, np.inf)
    se[columns] = np.sqrt(np.maximum(np.diag(cov), 0.0)) * layout.scale[columns]
    diff = ivv - ls
    moved = [i for i in range(layout.size) if columns[i] and abs(diff[i]) > Z_LIMIT * se[i]
             and abs(diff[i]) > RELATIVE_LIMIT * max(abs(ls[i]), 1e-300)]
    if not moved:
        return []
    text = ", ".join(f"'{layout.labels[i]}' {ls[i]:.4g} -> {ivv[i]:.4g} (difference ±{se[i]:.2g})" for i in moved)
    return [FitWarning(
        code=CODE,
        message="equation error looks biased by noise in the regressors (errors in variables, or coloured "
                "equation noise that correlates with them): an instrumental-variable re-estimate, with the "
                f"model's own noise-free simulation as instruments, moves {text}. Least squares on noisy "
                "states is biased however long the record; use a prefilter (options.prefilter, as in Robust "
                "parameter estimation by noise reduction), an output-error method (single_shooting, "
                "multiple_shooting), or take the IV values as a start",
        detail={"parameters": [layout.labels[i] for i in moved],
                "least_squares": {layout.labels[i]: float(ls[i]) for i in moved},
                "instrumental": {layout.labels[i]: float(ivv[i]) for i in moved},
                "difference_stderr": {layout.labels[i]: float(se[i]) for i in moved}})]


def equation_error_bias_warnings(eep: EquationErrorProblem, cm, data, layout: ParameterLayout, w: np.ndarray,
                                 columns: np.ndarray, options) -> list[FitWarning]:
    """The check as `fit_model` calls it (after the least-squares fit; `columns`: not on a bound).

    Parameters
    ----------
    eep : EquationErrorProblem
        The equation-error problem that was solved.
    cm : CompiledModel
        The compiled model.
    data : list of ExperimentData
        The experiments.
    layout : ParameterLayout
        The free parameters and their scaling.
    w : numpy.ndarray
        The least-squares solution (scaled θ first; extra entries are ignored).
    columns : numpy.ndarray
        Boolean mask of the parameters not on a bound.
    options : FitOptions
        Integration options and the derivative window.

    Returns
    -------
    list of FitWarning
        One `errors_in_variables_bias` warning when the IV re-estimate moves a parameter significantly,
        else empty (also when no parameter is free of its bounds, `w` is not finite, or there are no instruments).
    """
    w = np.asarray(w, float)[:layout.size]
    if not np.any(columns) or not np.all(np.isfinite(w)):
        return []
    z = simulated_instruments(eep, cm, data, layout, w, options)
    if z is None:
        return []
    bandwidth = hac_bandwidth(eep, cm.model.discrete is not None, options.derivative_window)
    return errors_in_variables_warnings(eep, layout, w, z, columns, bandwidth)
