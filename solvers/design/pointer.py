"""The design request that would settle what a fit or a discovery left open.

A discovery step the data cannot decide (`ambiguous`) and a fit whose parameters the input did not
excite (`poor_excitation`) both end in the same advice: run another experiment. This module writes
that experiment's design request (POST /v1/designs), taking what it needs from the record that was
fitted: the inputs' ranges as their limits, the residual's RMSE as each output's noise, the record's
length and sampling, and the fitted initial state.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from greyfit.schemas.fit import FitRequest, FitResult
from greyfit.schemas.model import Model


def with_estimates(model: Model, fit: FitResult) -> dict[str, Any]:
    """The model as a dict whose parameter values are the fit's estimates (inside their bounds).

    Parameters
    ----------
    model : Model
        The model.
    fit : FitResult
        Its fit.

    Returns
    -------
    dict
        The model's JSON body.
    """
    body = model.model_dump(exclude_none=True)
    for par in body.get("parameters", []):
        est = fit.parameters.get(par["name"])
        if est is not None and np.isfinite(est.value):
            lo, hi = par.get("lower", -np.inf), par.get("upper", np.inf)
            par["value"] = float(min(max(est.value, lo), hi))
    return body


def _record_frame(request: FitRequest, fit: FitResult) -> dict[str, Any]:
    exp = request.experiments[0]
    time = np.asarray(exp.time, dtype=float)
    limits = {}
    for name, series in exp.inputs.items():
        values = np.array([v for v in series if v is not None], dtype=float)
        lo, hi = (float(values.min()), float(values.max())) if values.size else (0.0, 0.0)
        if hi <= lo:   # a constant input (a step from rest): between rest and the level it held
            lo, hi = min(lo, 0.0), max(hi, 0.0)
        limits[name] = {"lower": lo, "upper": hi} if hi > lo else {"value": lo}
    noise = {name: float(r) for name, r in fit.metrics.rmse.items() if r is not None and r > 0}
    initial = fit.initial_states.get(exp.name, {})
    return {"inputs": limits, "outputs": noise, "duration": float(time[-1] - time[0]),
            "sample_time": float(np.median(np.diff(time))),
            "initial_state": {k: float(v) for k, v in initial.items() if np.isfinite(v)}}


def discrimination_request(name: str, model: Model, fit: FitResult, request: FitRequest,
                           rivals: list[tuple[str, Model, FitResult]]) -> dict[str, Any]:
    """The T-optimal design request telling `model` (as fitted) from each rival (as fitted).

    Parameters
    ----------
    name : str
        What the chosen model is called in the design (e.g. the effect it adds).
    model : Model
        The chosen model.
    fit : FitResult
        Its fit.
    request : FitRequest
        The fit's request (its first record frames the design).
    rivals : list of (name, Model, FitResult)
        The rivals the data could not tell from it.

    Returns
    -------
    dict
        A body for POST /v1/designs (a `DesignRequest`).
    """
    body = _record_frame(request, fit)
    body.update({"model": {**with_estimates(model, fit), "name": name}, "criterion": "T",
                 "rivals": [{"name": rival, "model": {**with_estimates(m, f), "name": rival}}
                            for rival, m, f in rivals]})
    return body
