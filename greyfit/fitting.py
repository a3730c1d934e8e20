"""`greyfit.fit` as a Python user calls it, and a result that simulates and predicts on new records.

`fit` takes a `FitRequest`, its dict, or the request's fields as keyword arguments; it returns a
`FitResult` (the schema's, with `simulate` and `predict`). Both call the solvers the command line and
the service call, so the numbers are theirs.
"""
from __future__ import annotations

from typing import Any, Sequence, Union

from greyfit.schemas.experiment import Experiment
from greyfit.schemas.fit import FitRequest
from greyfit.schemas.fit import FitResult as FitResultSchema
from greyfit.schemas.simulate import SimulateRequest, SimulateResult

Records = Union[Experiment, dict, Sequence[Union[Experiment, dict]]]


class FitResult(FitResultSchema):
    """The result of a fit (every field of `greyfit.schemas.FitResult`), which also runs its model on
    other records: `simulate` (the free simulation, as SITB's `sim`/`compare`) and `predict` (k-step
    ahead, as SITB's `predict`). The model and estimates are those the result carries."""

    def simulate(self, experiments: Records, **options: Any) -> SimulateResult:
        """The model with this result's estimates simulated on `experiments` (outputs optional: where
        given, `validation` holds fit % and RMSE against them).

        `options` are SimulateRequest's: `initial_states`, `estimate_window`, `parameters` (overrides)."""
        from greyfit.solvers.simulation.simulate import simulate_request
        return simulate_request(SimulateRequest(fit_result=self, experiments=_records(experiments), **options))

    def predict(self, experiments: Records, horizon: int = 1, **options: Any) -> SimulateResult:
        """ŷ(t | t - horizon) on `experiments`: the model restarted `horizon` samples earlier from the
        measured states, in each record's `predicted` (the measured outputs are needed)."""
        return self.simulate(experiments, horizon=horizon, **options)


def fit(request: Union[FitRequest, dict, None] = None, /, **fields: Any) -> FitResult:
    """Fit a model to records: `fit(request)`, `fit(request_dict)` or `fit(model=..., experiments=[...],
    method=..., options={...}, validation=[...])`.

    Returns the `FitResult`; an invalid request raises pydantic's ValidationError naming the field, a
    model or data the solver cannot use raises `greyfit.solvers.errors.FitError`.
    """
    from greyfit.solvers.fit import fit_model
    if request is not None and fields:
        raise TypeError("give a request or its fields as keywords, not both")
    if request is None:
        if "experiments" in fields and isinstance(fields["experiments"], (Experiment, dict)):
            fields["experiments"] = [fields["experiments"]]
        request = fields
    if not isinstance(request, FitRequest):
        request = FitRequest.model_validate(request)
    return as_result(fit_model(request))


def as_result(result: FitResultSchema) -> FitResult:
    """The schema's result as `greyfit.FitResult` (the same fields, not validated again)."""
    if isinstance(result, FitResult):
        return result
    return FitResult.model_construct(_fields_set=set(result.model_fields_set),
                                     **{name: getattr(result, name) for name in type(result).model_fields})


def _records(experiments: Records) -> list:
    if isinstance(experiments, (Experiment, dict)):
        return [experiments]
    return list(experiments)
