"""Smooth inputs on a finer time grid: a cubic reading of sampled inputs between their samples.

A physical input sampled by an instrument (a force, a voltage, a heater's power) varies smoothly
between its samples. Read as linear between them (first-order hold), a sum of sines at ω·Δt = 0.2
is off by up to (ωΔt)²/8 ≈ 0.5 % of its amplitude; on a long, quiet record that is enough to move an
estimate by several of its standard errors. A cubic Hermite interpolant whose slopes come from a
five-point difference is off by O((ωΔt)⁴) instead (≈ 4·10⁻⁶ there). The integrators take inputs at
the ends of each interval, so the cubic reading is given to them as the same record on a grid
`factor` times finer: the inputs evaluated on it, the outputs missing (null) between the original
samples, so the residual, its weights and every count stay those of the original samples.
"""
from __future__ import annotations

import math

import numpy as np

from greyfit.schemas.experiment import Experiment

# the shift of an estimate (in standard errors) left by the linear reading of the fine grid is the
# coarse one over factor², so a factor of 4 makes a shift of 1 standard error 0.06
DEFAULT_FACTOR = 4
MAX_FACTOR = 8


def hermite_slopes(t: np.ndarray, u: np.ndarray) -> np.ndarray:
    """du/dt at the samples: five-point differences on a uniform grid (error O(Δt⁴), one-sided at
    its ends), second-order ones on a non-uniform grid.

    Parameters
    ----------
    t : numpy.ndarray
        Sample times, strictly increasing, shape (n,).
    u : numpy.ndarray
        The series, shape (n,) or (m, n).

    Returns
    -------
    numpy.ndarray
        The slopes, the shape of `u`.
    """
    u = np.asarray(u, dtype=float)
    if t.size < 3:
        return np.repeat(np.diff(u, axis=-1) / np.diff(t), t.size, axis=-1)
    m = np.gradient(u, t, axis=-1, edge_order=2)
    h = np.diff(t)
    if t.size >= 5 and np.ptp(h) <= 1e-9 * h.mean():
        d = 12 * h.mean()
        m[..., 2:-2] = (u[..., :-4] - 8 * u[..., 1:-3] + 8 * u[..., 3:-1] - u[..., 4:]) / d
        # fourth-order one-sided differences at the two ends of each side
        a = u[..., :5]
        m[..., 0] = (-25 * a[..., 0] + 48 * a[..., 1] - 36 * a[..., 2] + 16 * a[..., 3] - 3 * a[..., 4]) / d
        m[..., 1] = (-3 * a[..., 0] - 10 * a[..., 1] + 18 * a[..., 2] - 6 * a[..., 3] + a[..., 4]) / d
        b = u[..., -5:]
        m[..., -1] = (25 * b[..., 4] - 48 * b[..., 3] + 36 * b[..., 2] - 16 * b[..., 1] + 3 * b[..., 0]) / d
        m[..., -2] = (3 * b[..., 4] + 10 * b[..., 3] - 18 * b[..., 2] + 6 * b[..., 1] - b[..., 0]) / d
    return m


def cubic_on_finer_grid(t: np.ndarray, u: np.ndarray, factor: int) -> tuple[np.ndarray, np.ndarray]:
    """The grid `factor` times finer than `t` and the cubic Hermite reading of `u` on it.

    Parameters
    ----------
    t : numpy.ndarray
        Sample times, shape (n,).
    u : numpy.ndarray
        The series, shape (m, n): one row per input.
    factor : int
        Points per original interval on the new grid (≥ 1); the original samples are every
        `factor`-th point of it.

    Returns
    -------
    t_fine : numpy.ndarray
        Shape ((n − 1)·factor + 1,).
    u_fine : numpy.ndarray
        Shape (m, (n − 1)·factor + 1); equal to `u` at the original samples.
    """
    u = np.atleast_2d(np.asarray(u, dtype=float))
    h = np.diff(t)
    tau = np.arange(factor) / factor
    h00, h10 = 2 * tau ** 3 - 3 * tau ** 2 + 1, tau ** 3 - 2 * tau ** 2 + tau
    h01, h11 = -2 * tau ** 3 + 3 * tau ** 2, tau ** 3 - tau ** 2
    m = hermite_slopes(t, u)
    left, right = m[:, :-1] * h, m[:, 1:] * h      # the slopes in units of each interval
    fine = (u[:, :-1, None] * h00 + left[:, :, None] * h10 + u[:, 1:, None] * h01
            + right[:, :, None] * h11).reshape(u.shape[0], -1)
    t_fine = (t[:-1, None] + h[:, None] * tau).ravel()
    return np.append(t_fine, t[-1]), np.concatenate([fine, u[:, -1:]], axis=1)


def linear_on_finer_grid(t: np.ndarray, u: np.ndarray, factor: int) -> np.ndarray:
    """The first-order-hold reading of `u` on the grid of `cubic_on_finer_grid` (shape (m, ·)).

    Parameters
    ----------
    t : numpy.ndarray
        Sample times, shape (n,).
    u : numpy.ndarray
        The series, shape (m, n).
    factor : int
        Points per original interval.

    Returns
    -------
    numpy.ndarray
        Shape (m, (n − 1)·factor + 1).
    """
    u = np.atleast_2d(np.asarray(u, dtype=float))
    tau = np.arange(factor) / factor
    fine = (u[:, :-1, None] * (1 - tau) + u[:, 1:, None] * tau).reshape(u.shape[0], -1)
    return np.concatenate([fine, u[:, -1:]], axis=1)


def refine_experiment(exp: Experiment, factor: int) -> Experiment:
    """The record on a grid `factor` times finer: every input read as a cubic between its samples,
    outputs and derivatives missing between the original samples.

    Parameters
    ----------
    exp : Experiment
        A complete record (its inputs have no missing values); its `preprocess` already applied.
    factor : int
        Points per original interval.

    Returns
    -------
    Experiment
        The same record on the finer grid; the record itself when `factor` is 1 or it has no input.
    """
    if factor <= 1 or not exp.inputs:
        return exp
    t = np.asarray(exp.time, dtype=float)
    names = list(exp.inputs)
    t_fine, u_fine = cubic_on_finer_grid(t, np.array([exp.inputs[n] for n in names], dtype=float), factor)

    def sparse(values: list) -> list:
        out: list = [None] * t_fine.size
        out[::factor] = values
        return out
    return exp.model_copy(update={
        "time": t_fine.tolist(), "inputs": {n: u_fine[i].tolist() for i, n in enumerate(names)},
        "outputs": {k: sparse(v) for k, v in exp.outputs.items()},
        "derivatives": {k: sparse(v) for k, v in exp.derivatives.items()}, "preprocess": None})


def factor_for(shift: float, target: float = 0.1) -> int:
    """The refinement that leaves a linear-reading shift of `shift` standard errors at about `target`.

    Parameters
    ----------
    shift : float
        The estimated shift of the worst estimate, in standard errors, on the original grid.
    target : float
        The shift acceptable on the finer grid.

    Returns
    -------
    int
        Between `DEFAULT_FACTOR` and `MAX_FACTOR` (the shift falls as factor²).
    """
    return int(min(max(DEFAULT_FACTOR, math.ceil(math.sqrt(max(shift, 0.0) / target))), MAX_FACTOR))


def refine_options(options, factor: int):
    """Fit options for records refined by `factor`: linear on the finer grid, substeps divided.

    Parameters
    ----------
    options : FitOptions
        The options for the original records.
    factor : int
        Points per original interval.

    Returns
    -------
    FitOptions
        ``input_interpolation`` foh and ``substeps`` ⌈substeps / factor⌉ (the same step or a shorter one).
    """
    return options.model_copy(update={"input_interpolation": "foh",
                                      "substeps": max(1, math.ceil(options.substeps / factor))})


def refine_request(request, factor: int):
    """The request with its estimation and validation records on a grid `factor` times finer, the
    inputs read as cubics (`refine_experiment`), linear interpolation on that grid, and the RK4
    substeps divided by `factor` (the same step or a shorter one).

    Parameters
    ----------
    request : pydantic.BaseModel
        A fit or simulate request with `experiments`, `options` and perhaps `validation`.
    factor : int
        Points per original interval.

    Returns
    -------
    pydantic.BaseModel
        The refined copy.
    """
    update = {"experiments": [refine_experiment(e, factor) for e in request.experiments],
              "options": refine_options(request.options, factor)}
    if getattr(request, "validation", None):
        update["validation"] = [refine_experiment(e, factor) for e in request.validation]
    return request.model_copy(update=update)


def thin_traces(result, factor: int):
    """A fit result's traces back on the original samples (every `factor`-th point of the finer grid).

    Parameters
    ----------
    result : FitResult
        A result fitted on a grid `factor` times finer than the records.
    factor : int
        Points per original interval.

    Returns
    -------
    FitResult
        The same result (changed in place): `traces` and the validation records' `time` and
        `simulated` thinned.
    """
    for tr in result.traces or []:
        tr.time = tr.time[::factor]
        tr.simulated = {k: v[::factor] for k, v in tr.simulated.items()}
        tr.residuals = {k: v[::factor] for k, v in tr.residuals.items()}
    for ev in result.validation.experiments if result.validation is not None else []:
        if ev.time is not None:
            ev.time = ev.time[::factor]
        if ev.simulated is not None:
            ev.simulated = {k: v[::factor] for k, v in ev.simulated.items()}
    return result
