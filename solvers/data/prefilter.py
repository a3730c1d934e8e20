"""Prefilters against measurement noise: the same stable low-pass on both sides of the equation.

Equation error and ARX are biased when the regressors carry measurement noise (Robust parameter
estimation by noise reduction, Aoki and Kawata). A low-pass F applied to outputs *and* inputs keeps
the input-output relation of a linear model (F commutes with it) while the noise above the cut-off
is removed from the regressors.

* Discrete-time models: the noise-reduction paper's first-order H_f(z) = (1 − a_f)/(1 − a_f z⁻¹),
  a_f = exp(−2π f_c Ts), applied `order` times (unit DC gain; the gain cancels anyway).
* Continuous-time models (state-variable filter): `order` cascaded ω/(s + ω), ω = 2π f_c,
  integrated exactly for inputs linear between samples. The derivative of the filtered state is
  the filter's own ω(F^{n-1}x − F^n x): no numerical differentiation of the noisy data.

The filter start-up (the data before the filter has settled) is dropped.
"""
from __future__ import annotations

import math
from dataclasses import replace

import casadi as ca
import numpy as np

from greyfit.schemas.online import Prefilter
from greyfit.solvers.data.experiments import ExperimentData
from greyfit.solvers.errors import DataError
from greyfit.solvers.model.compiler import CompiledModel

SETTLING_TIME_CONSTANTS = 5


def lowpass_discrete(x: np.ndarray, a: float) -> np.ndarray:
    """y[k] = a y[k-1] + (1 − a) x[k] along the last axis, started at rest on x[0].

    Parameters
    ----------
    x : numpy.ndarray
        Signals, samples along the last axis, shape (..., N).
    a : float
        Pole of the filter, a_f = exp(−2π f_c Ts), in [0, 1).

    Returns
    -------
    numpy.ndarray
        Filtered signals, same shape as `x`.
    """
    y = np.empty_like(x)
    y[..., 0] = x[..., 0]
    for k in range(1, x.shape[-1]):
        y[..., k] = a * y[..., k - 1] + (1 - a) * x[..., k]
    return y


def lowpass_continuous(x: np.ndarray, t: np.ndarray, omega: float) -> np.ndarray:
    """Exact response of z' = ω(x − z) to x linear between samples, started at rest on x[0].

    Parameters
    ----------
    x : numpy.ndarray
        Signals, samples along the last axis, shape (..., N).
    t : numpy.ndarray
        Sample times, shape (N,).
    omega : float
        Cut-off angular frequency ω = 2π f_c, in rad per time unit.

    Returns
    -------
    numpy.ndarray
        Filtered signals, same shape as `x`.
    """
    z = np.empty_like(x)
    z[..., 0] = x[..., 0]
    dt = np.diff(t)
    a = np.exp(-omega * dt)
    c = 1 - (1 - a) / (omega * dt)
    for k in range(x.shape[-1] - 1):
        z[..., k + 1] = a[k] * z[..., k] + (1 - a[k]) * x[..., k] + c[k] * (x[..., k + 1] - x[..., k])
    return z


def _settling_samples(spec: Prefilter, t: np.ndarray) -> int:
    tau = 1.0 / (2 * math.pi * spec.cutoff_hz)
    return int(np.searchsorted(t - t[0], SETTLING_TIME_CONSTANTS * spec.order * tau))


def is_linear_in_states_and_inputs(cm: CompiledModel) -> bool:
    """Whether the model's right-hand side is affine in its states and inputs.

    The state-variable filter commutes exactly only with such a model; for others it is an
    approximation, and the prefilter's note says so.

    Parameters
    ----------
    cm : CompiledModel
        The compiled model.

    Returns
    -------
    bool
        True when ∂f/∂(x, u) depends on neither x, u nor t.
    """
    x, u, p, t = ca.SX.sym("x", cm.nx), ca.SX.sym("u", cm.nu), ca.SX.sym("p", cm.np), ca.SX.sym("t")
    z = ca.vertcat(x, u)
    return not ca.depends_on(ca.jacobian(cm.rhs(x, u, p, t), z), ca.vertcat(z, t))


def apply_prefilter(cm: CompiledModel, data: list[ExperimentData], spec: Prefilter) -> tuple[list[ExperimentData], str]:
    """Filtered copies of the experiments and a description for `solver.derivative_filter`.

    Outputs and inputs are filtered alike; for a continuous-time model the derivatives of the
    directly measured states come from the filter itself. The first samples, while the filter
    settles (5 time constants per order), are set missing.

    Parameters
    ----------
    cm : CompiledModel
        The compiled model (discrete or continuous time).
    data : list of ExperimentData
        Prepared experiments with complete outputs.
    spec : Prefilter
        Cut-off frequency `cutoff_hz` (Hz) and `order` of the filter.

    Returns
    -------
    data : list of ExperimentData
        Filtered copies, outputs NaN during the settling samples.
    note : str
        What was applied, noting when the model is not linear in its states and inputs.

    Raises
    ------
    DataError
        When an experiment has missing output samples (``experiments[e].outputs``), or is too short
        for the filter to settle (``experiments[e].time``).
    """
    discrete = cm.model.discrete
    out = []
    for e, d in enumerate(data):
        if np.isnan(d.y).any():
            raise DataError("a prefilter needs complete outputs (no null samples); fill or trim them",
                            f"experiments[{e}].outputs")
        drop = _settling_samples(spec, d.t)
        if drop >= d.n - 2:
            raise DataError(f"the prefilter needs {drop} samples to settle and the experiment has "
                            f"{d.n}; raise options.prefilter.cutoff_hz or give a longer record",
                            f"experiments[{e}].time")
        if discrete is not None:
            a = math.exp(-2 * math.pi * spec.cutoff_hz * discrete.sample_time)
            y, u = d.y, d.u
            for _ in range(spec.order):
                y, u = lowpass_discrete(y, a), lowpass_discrete(u, a)
            derivatives = {}
        else:
            omega = 2 * math.pi * spec.cutoff_hz
            y_prev, y, u = d.y, d.y, d.u
            for _ in range(spec.order):
                y_prev, y = y, lowpass_continuous(y, d.t, omega)
                u = lowpass_continuous(u, d.t, omega)
            derivatives = {cm.states.index(state): omega * (y_prev[j] - y[j])
                           for j, state in ((cm.outputs.index(o), s) for o, s in cm.direct_outputs.items())}
        y = y.copy()
        y[:, :drop] = np.nan
        for v in derivatives.values():
            v[:drop] = np.nan
        out.append(replace(d, y=y, u=u, derivatives=derivatives))
    if discrete is not None:
        note = (f"prefilter: {spec.order} x first-order low-pass (1-a)/(1-a z^-1), "
                f"f_c = {spec.cutoff_hz:g} Hz, on outputs and inputs")
    else:
        note = (f"state-variable filter: (w/(s+w))^{spec.order}, f_c = {spec.cutoff_hz:g} Hz, on states "
                f"and inputs; derivative w(F^(n-1)x - F^n x)")
        if not is_linear_in_states_and_inputs(cm):
            note += " (approximate: the model is not linear in its states and inputs)"
    return out, note
