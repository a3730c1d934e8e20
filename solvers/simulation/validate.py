"""Validation records of a fit: simulate the fitted model on them and compare (MATLAB compare).

Initial state of a validation record, in this order: its own `initial_state`; where it continues an
estimation record (its first sample is that record's last one, or one sample step after it), the
state the fitted model reached there ("contiguous", output-error fits only); else the free states
fitted on a short leading window with the parameters fixed ("estimated").
"""
from __future__ import annotations

import numpy as np

from greyfit.schemas.experiment import Experiment
from greyfit.schemas.fit import FitRequest, FitResult
from greyfit.schemas.validation import ValidationResult
from greyfit.solvers.dynamics.integration import make_step
from greyfit.solvers.methods.registry import simulates_outputs
from greyfit.solvers.model.compiler import CompiledModel, compile_model
from greyfit.solvers.simulation.simulate import parameter_vector, simulate_arrays, validation_from

CONTIGUITY_TOLERANCE = 1e-6   # relative to the estimation record's last time step


def _continues(val: Experiment, est: Experiment) -> str | None:
    """'same' if val starts at est's last sample, 'next' if one step later, else None."""
    dt = est.time[-1] - est.time[-2]
    gap = val.time[0] - est.time[-1]
    if abs(gap) <= CONTIGUITY_TOLERANCE * dt:
        return "same"
    if abs(gap - dt) <= CONTIGUITY_TOLERANCE * dt:
        return "next"
    return None


def _contiguous_states(request: FitRequest, result: FitResult, cm: CompiledModel, params: dict[str, float],
                       ) -> tuple[dict[str, dict[str, float]], dict[str, str], dict[str, str]]:
    """Initial states of the validation records that continue an estimation record.

    Returns (initial states, source per record, estimation record each one continues).
    """
    pairs = {}
    for v in request.validation:
        for est in request.experiments:
            kind = _continues(v, est)
            if kind:
                pairs[v.name] = (est, kind)
                break
    if not pairs or not simulates_outputs(request.method):
        return {}, {}, {}
    ests = list({est.name: est for est, _ in pairs.values()}.values())
    sims = simulate_arrays(request.model, params, ests, request.options, result.initial_states, cm=cm)
    end = {s.data.name: s for s in sims}
    step = make_step(cm, request.options)
    states, sources, parent = {}, {}, {}
    for v in request.validation:
        if v.name not in pairs:
            continue
        est, kind = pairs[v.name]
        sim = end[est.name]
        x = sim.states[:, -1]
        if kind == "next":   # one more step across the boundary, inputs from both records
            d = sim.data
            u1 = np.array([v.inputs[u][0] for u in cm.inputs], dtype=float)
            x = np.array(step(x, d.u[:, -1], u1, sim.p, d.t[-1], v.time[0] - d.t[-1])).ravel()
        states[v.name] = {s: float(x[i]) for i, s in enumerate(cm.states)}
        sources[v.name] = "contiguous"
        parent[v.name] = est.name
    return states, sources, parent


def validate_fit(request: FitRequest, result: FitResult, cm: CompiledModel | None = None) -> ValidationResult:
    """Simulation metrics of the fitted model on `request.validation` (already preprocessed).

    Validation records that continue an estimation record start from the state the fitted model
    reached there and take over its per-experiment parameter estimates; the others start from their
    own or estimated initial states.

    Parameters
    ----------
    request : FitRequest
        The fit request, its `validation` records already preprocessed.
    result : FitResult
        The fit's result (parameters and initial states).
    cm : CompiledModel or None, optional
        The compiled `request.model`, when the caller has it already.

    Returns
    -------
    ValidationResult
        Pooled and per-record metrics, with traces when `options.return_traces` is set.

    Raises
    ------
    DataError
        When a validation record needs a per-experiment parameter the fit did not give it
        (``parameters.<name>``), or as `simulate_arrays`.
    """
    cm = cm or compile_model(request.model)
    params = {k: v.value for k, v in result.parameters.items()}
    states, sources, parent = _contiguous_states(request, result, cm, params)
    # per-experiment estimates carry over to the record that continues their experiment
    for v_name, e_name in parent.items():
        for label, value in list(params.items()):
            if label.endswith(f"[{e_name}]"):
                params[f"{label.split('[', 1)[0]}[{v_name}]"] = value
    for v in request.validation:   # fail early with the field path of the validation record
        parameter_vector(request.model, params, v.name)
    sims = simulate_arrays(request.model, params, request.validation, request.options, states,
                           provided_source=sources, cm=cm)
    return validation_from(cm, sims, traces=request.options.return_traces)
