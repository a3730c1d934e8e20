"""A design request made concrete: the compiled model, parameter values, what is free, the grid and the signal.

Every check of the request that needs the model happens here, before any optimisation is paid for,
and names the field to fix.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from greyfit.schemas.design import DesignRequest
from greyfit.schemas.experiment import Experiment
from greyfit.schemas.model import Model
from greyfit.solvers.design.signal import Signal, design_grid, make_signal
from greyfit.solvers.design.simulation import Measured, measured_outputs
from greyfit.solvers.errors import DataError, ModelDefinitionError
from greyfit.solvers.model.compiler import CompiledModel, compile_model


@dataclass
class Candidate:
    """One model with its parameter values: the full vector and which entries are free."""

    name: str
    cm: CompiledModel
    p: np.ndarray
    free: tuple[int, ...]
    lower: np.ndarray      # bounds of the free entries
    upper: np.ndarray
    measured: Measured

    @property
    def free_names(self) -> list[str]:
        """Names of the free parameters.

        Returns
        -------
        list of str
            The free parameters' names.
        """
        return [self.cm.parameters[i] for i in self.free]


@dataclass
class DesignSetup:
    """What every criterion needs."""

    model: Candidate
    interest: list[int]                 # positions among the model's free parameters
    covariance: Optional[np.ndarray]    # of the free parameters, from fit_result
    x0: np.ndarray
    time: np.ndarray
    signal: Signal


def _model(request: DesignRequest) -> Model:
    if request.model is not None:
        return request.model
    model = request.fit_result.model if request.fit_result is not None else None
    if not isinstance(model, Model):
        raise ModelDefinitionError("fit_result carries no ODE model to design for; give `model`", "model")
    return model


def candidate(model: Model, values: dict[str, float], outputs: dict[str, float], field: str) -> Candidate:
    """Compile `model` and set its parameters: declared values overridden by `values`.

    Parameters
    ----------
    model : Model
        The model.
    values : dict
        Parameter values overriding the declared ones.
    outputs : dict
        The measured outputs and their noise levels.
    field : str
        Where the model sits in the request (for errors).

    Returns
    -------
    Candidate
    """
    if model.discrete is not None:
        raise ModelDefinitionError("experiment design takes continuous-time models", f"{field}.discrete")
    for par in model.parameters:
        if par.time_varying is not None:
            raise ModelDefinitionError(f"parameter {par.name!r} is time-varying; design for constant parameters",
                                       f"{field}.parameters")
    cm = compile_model(model)
    declared = {par.name: par for par in model.parameters}
    p = np.array([values.get(name, declared[name].value) for name in cm.parameters], dtype=float)
    free = tuple(i for i, name in enumerate(cm.parameters) if not declared[name].fixed)
    lower = np.array([-np.inf if declared[cm.parameters[i]].lower is None else declared[cm.parameters[i]].lower
                      for i in free], dtype=float)
    upper = np.array([np.inf if declared[cm.parameters[i]].upper is None else declared[cm.parameters[i]].upper
                      for i in free], dtype=float)
    return Candidate(model.name, cm, p, free, lower, upper, measured_outputs(cm, outputs, "outputs"))


def _values(request: DesignRequest, model: Model) -> dict[str, float]:
    names = {par.name for par in model.parameters}
    values: dict[str, float] = {}
    if request.fit_result is not None:
        values.update({name: est.value for name, est in request.fit_result.parameters.items() if name in names})
    for name, value in request.parameters.items():
        if name not in names:
            raise ModelDefinitionError(f"{name!r} is not a parameter of the model", f"parameters.{name}")
        values[name] = value
    return values


def _check_inputs(request: DesignRequest, cm: CompiledModel) -> None:
    for name in cm.inputs:
        if name not in request.inputs:
            raise DataError(f"the model's input {name!r} has no limits: give lower and upper (designed) or "
                            "value (held)", f"inputs.{name}")
    for name in request.inputs:
        if name not in cm.inputs:
            raise DataError(f"{name!r} is not an input of the model (its inputs: {', '.join(cm.inputs) or 'none'})",
                            f"inputs.{name}")
    if not any(limits.free for limits in request.inputs.values()):
        raise DataError("no input is free to design: give one input lower and upper instead of value", "inputs")


def _interest(request: DesignRequest, model: Candidate) -> list[int]:
    names = model.free_names
    if not names:
        raise ModelDefinitionError("every parameter is fixed: there is nothing to design for", "model.parameters")
    if not request.parameters_of_interest:
        return list(range(len(names)))
    for name in request.parameters_of_interest:
        if name not in names:
            raise ModelDefinitionError(f"{name!r} is not a free parameter of the model (free: {', '.join(names)})",
                                       "parameters_of_interest")
    return [names.index(name) for name in request.parameters_of_interest]


def _covariance(request: DesignRequest, model: Candidate) -> Optional[np.ndarray]:
    cov = request.fit_result.covariance if request.fit_result is not None else None
    names = model.free_names
    if cov is None or not set(names) <= set(cov.names):
        if request.robust_draws:
            raise DataError("robust_draws needs fit_result with a covariance of every free parameter",
                            "robust_draws")
        return None
    idx = [cov.names.index(name) for name in names]
    return np.asarray(cov.matrix, dtype=float)[np.ix_(idx, idx)]


def initial_state(cm: CompiledModel, given: dict[str, float], field: str) -> np.ndarray:
    """The initial state vector (0 where not given).

    Parameters
    ----------
    cm : CompiledModel
        The model.
    given : dict
        State name -> value.
    field : str
        Where the values sit in the request (for errors).

    Returns
    -------
    numpy.ndarray
        One value per state.
    """
    for name in given:
        if name not in cm.states:
            raise DataError(f"{name!r} is not a state of the model", f"{field}.{name}")
    return np.array([given.get(name, 0.0) for name in cm.states], dtype=float)


def design_setup(request: DesignRequest) -> DesignSetup:
    """Check the request against its model and lay out the design.

    Parameters
    ----------
    request : DesignRequest
        The request.

    Returns
    -------
    DesignSetup
    """
    model = _model(request)
    main = candidate(model, _values(request, model), request.outputs, "model")
    _check_inputs(request, main.cm)
    time = design_grid(request)
    return DesignSetup(main, _interest(request, main), _covariance(request, main),
                       initial_state(main.cm, request.initial_state, "initial_state"), time,
                       make_signal(request, main.cm.inputs, time))


def baseline_inputs(request: DesignRequest, inputs: list[str], baseline: Experiment) -> np.ndarray:
    """The baseline's inputs as a matrix on its own samples (held inputs from the request where absent).

    Parameters
    ----------
    request : DesignRequest
        Held inputs' values.
    inputs : list of str
        The model's inputs in order.
    baseline : Experiment
        The baseline record.

    Returns
    -------
    numpy.ndarray
        Inputs × samples.
    """
    n = len(baseline.time)
    U = np.zeros((len(inputs), n))
    for i, name in enumerate(inputs):
        series = baseline.inputs.get(name)
        if series is None:
            limits = request.inputs[name]
            if limits.value is None:
                raise DataError(f"the baseline has no series for the designed input {name!r}",
                                f"baseline.inputs.{name}")
            U[i, :] = limits.value
            continue
        values = np.array([np.nan if v is None else v for v in series], dtype=float)
        if len(values) != n or not np.all(np.isfinite(values)):
            raise DataError(f"the series must have {n} finite values (one per time sample)",
                            f"baseline.inputs.{name}")
        U[i, :] = values
    return U


def baseline_time(baseline: Experiment) -> np.ndarray:
    """The baseline's sample times, checked increasing.

    Parameters
    ----------
    baseline : Experiment
        The baseline record.

    Returns
    -------
    numpy.ndarray
        Its sample times.
    """
    time = np.asarray(baseline.time, dtype=float)
    if not np.all(np.isfinite(time)) or np.any(np.diff(time) <= 0):
        raise DataError("time must be finite and strictly increasing", "baseline.time")
    return time
