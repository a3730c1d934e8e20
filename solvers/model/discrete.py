"""Discrete-time models: x[k+1] = f(x[k], u[k], θ, t_k) in `equations`, `model.discrete.sample_time`.

The same methods fit them: equation error regresses the next sample x[k+1] on f (for an ARX
model this is the prediction-error / one-step-predictor fit), and output error simulates with the
step being f itself (`make_discrete_step`, used by `solvers.integration.make_step`).
Delay states (an equation that is just another state's or an input's name, such as ARX's
`y_1[k+1] = y[k]`) need not be measured: their series is the shifted source.
"""
from __future__ import annotations

import casadi as ca
import numpy as np

from greyfit.solvers.data.experiments import ExperimentData
from greyfit.solvers.errors import DataError
from greyfit.solvers.model.compiler import CompiledModel
from greyfit.solvers.model.expressions import parse

SAMPLE_TIME_RTOL = 1e-6


def is_discrete(cm: CompiledModel) -> bool:
    """Whether the model is a discrete-time (difference equation) model.

    Parameters
    ----------
    cm : CompiledModel
        The compiled model.

    Returns
    -------
    bool
        True when `model.discrete` is set.
    """
    return cm.model.discrete is not None


def make_discrete_step(cm: CompiledModel) -> ca.Function:
    """step(x, u0, u1, p, t0, dt) -> f(x, u0, p, t0): the same signature as the ODE integrators.

    Parameters
    ----------
    cm : CompiledModel
        A compiled discrete-time model.

    Returns
    -------
    casadi.Function
        The step; `u1` and `dt` are accepted and unused.
    """
    x, u0, u1 = ca.SX.sym("x", cm.nx), ca.SX.sym("u0", cm.nu), ca.SX.sym("u1", cm.nu)
    p, t0, dt = ca.SX.sym("p", cm.np), ca.SX.sym("t0"), ca.SX.sym("dt")
    return ca.Function("step", [x, u0, u1, p, t0, dt], [cm.rhs(x, u0, p, t0)])


def check_sample_time(cm: CompiledModel, data: list[ExperimentData]) -> None:
    """Every experiment must be sampled at exactly the model's Ts.

    Does nothing for a continuous-time model.

    Parameters
    ----------
    cm : CompiledModel
        The compiled model.
    data : list of ExperimentData
        The prepared experiments.

    Raises
    ------
    DataError
        When a time step differs from `model.discrete.sample_time` by more than `SAMPLE_TIME_RTOL`
        relative; names ``experiments[e].time``.
    """
    if cm.model.discrete is None:
        return
    ts = cm.model.discrete.sample_time
    for e, d in enumerate(data):
        steps = np.diff(d.t)
        bad = np.flatnonzero(np.abs(steps - ts) > SAMPLE_TIME_RTOL * ts)
        if bad.size:
            i = int(bad[0])
            raise DataError(
                f"time steps by {steps[i]:.6g} s between samples {i} and {i + 1}, the model's "
                f"sample_time is {ts:.6g} s; resample the data or change model.discrete.sample_time",
                f"experiments[{e}].time")


def delay_sources(cm: CompiledModel) -> dict[int, tuple[str, int]]:
    """State index -> ('state' | 'input', index) for states whose equation is a plain name.

    Parameters
    ----------
    cm : CompiledModel
        The compiled model.

    Returns
    -------
    dict of int to tuple of (str, int)
        For each delay state, whether its source is a state or an input, and the source's index.
    """
    out = {}
    for i, s in enumerate(cm.states):
        node = parse(cm.model.equations[s], f"equations.{s}")
        if node[0] == "name" and node[1] in cm.states:
            out[i] = ("state", cm.states.index(node[1]))
        elif node[0] == "name" and node[1] in cm.inputs:
            out[i] = ("input", cm.inputs.index(node[1]))
    return out


def state_series(cm: CompiledModel, d: ExperimentData, e: int) -> np.ndarray:
    """(nx, N) states: measured directly, or delay states rebuilt by shifting their source.

    Parameters
    ----------
    cm : CompiledModel
        A compiled discrete-time model.
    d : ExperimentData
        The prepared experiment.
    e : int
        Index of the experiment, for the error's field path.

    Returns
    -------
    numpy.ndarray
        State series, shape (nx, N); NaN where a measurement is missing and at the first sample of a
        delay state.

    Raises
    ------
    DataError
        When a state is neither measured directly nor a delay of a known signal; names
        ``experiments[e].outputs``.
    """
    x = np.full((cm.nx, d.n), np.nan)
    known = set()
    for out, state in cm.direct_outputs.items():
        i = cm.states.index(state)
        x[i] = d.y[cm.outputs.index(out)]
        known.add(i)
    sources = delay_sources(cm)
    progress = True
    while progress:
        progress = False
        for i, (kind, j) in sources.items():
            if i in known or (kind == "state" and j not in known):
                continue
            src = d.u[j] if kind == "input" else x[j]
            x[i, 1:] = src[:-1]     # x_i[k] = source[k-1]; the first sample is unknown
            known.add(i)
            progress = True
    missing = [cm.states[i] for i in range(cm.nx) if i not in known]
    if missing:
        raise DataError(
            f"equation error needs every state measured or a delay of a measured signal; state "
            f"'{missing[0]}' is neither. Use single_shooting or multiple_shooting, or measure it",
            f"experiments[{e}].outputs")
    return x


def next_state_data(cm: CompiledModel, d: ExperimentData, e: int) -> tuple[np.ndarray, np.ndarray]:
    """(x[k], x[k+1]) as (nx, N) arrays; x[k+1] of the last sample is NaN.

    Parameters
    ----------
    cm : CompiledModel
        A compiled discrete-time model.
    d : ExperimentData
        The prepared experiment.
    e : int
        Index of the experiment, for the error's field path.

    Returns
    -------
    x : numpy.ndarray
        States x[k], shape (nx, N), as `state_series`.
    next : numpy.ndarray
        States x[k+1], shape (nx, N).

    Raises
    ------
    DataError
        As `state_series`.
    """
    x = state_series(cm, d, e)
    nxt = np.full_like(x, np.nan)
    nxt[:, :-1] = x[:, 1:]
    return x, nxt


def armax_start(model, data: list[ExperimentData]):
    """An ARMAX template's model with its a, b guesses left at 0 started from the ARX least-squares fit.

    At a = b = c = 0 the predictor's output is zero, so ∂ŷ/∂a_i = −y[k−i] and ∂ŷ/∂c_i = y[k−i] are
    collinear and the start tells nothing apart; the ARX estimate (c = 0) is the classical start of
    the prediction-error fit. Declared non-zero guesses and fixed parameters are kept.

    Parameters
    ----------
    model : Model
        The model; only an ARMAX template's model is changed.
    data : list of ExperimentData
        Prepared experiments; the measured output enters as the input ``<output>_measured``.

    Returns
    -------
    Model
        A copy with the ARX estimates (clipped into the bounds) as the values of the free a, b
        parameters declared at 0; `model` itself when it is not ARMAX or the data are too few for
        the regression.
    """
    tpl = model.template
    if tpl is None or tpl.kind != "armax":
        return model
    y_name, u_name = tpl.output, tpl.input
    rows, targets = [], []
    for d in data:
        iy, iu = model.inputs.index(f"{y_name}_measured"), model.inputs.index(u_name)
        y, u = d.u[iy], d.u[iu]
        first = max(tpl.na, tpl.nk + tpl.nb - 1)
        for k in range(first, y.size):
            rows.append([-y[k - i] for i in range(1, tpl.na + 1)]
                        + [u[k - tpl.nk - j + 1] for j in range(1, tpl.nb + 1)])
            targets.append(y[k])
    if len(rows) <= tpl.na + tpl.nb:
        return model
    coef = np.linalg.lstsq(np.array(rows), np.array(targets), rcond=None)[0]
    start = dict(zip([f"a{i}" for i in range(1, tpl.na + 1)] + [f"b{j}" for j in range(1, tpl.nb + 1)], coef))
    params = []
    for p in model.parameters:
        if p.name in start and p.value == 0.0 and not p.fixed and np.isfinite(start[p.name]):
            lo = -np.inf if p.lower is None else p.lower
            hi = np.inf if p.upper is None else p.upper
            p = p.model_copy(update={"value": float(np.clip(start[p.name], lo, hi))})
        params.append(p)
    return model.model_copy(update={"parameters": params})
