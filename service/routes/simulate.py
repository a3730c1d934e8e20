from fastapi import APIRouter, Depends, Request

from schemas.simulate import SimulateRequest, SimulateResult
from service.deps import require_api_key
from service.limits import data_values
from service.problems import LimitExceeded, RequestTooLarge
from service.routes.fits import run_sync

router = APIRouter(prefix="/v1", tags=["simulate"], dependencies=[Depends(require_api_key)])


@router.post("/simulate", response_model=SimulateResult)
async def create_simulation(body: SimulateRequest, request: Request):
    """Simulate a model (parameters given, or from a previous fit/discovery result) on experiments."""
    settings = request.app.state.settings
    for i, exp in enumerate(body.experiments):
        if len(exp.time) > settings.max_samples_per_experiment:
            raise LimitExceeded(f"experiments[{i}].time", f"{len(exp.time)} samples, the limit is "
                                f"{settings.max_samples_per_experiment}; decimate or split the record")
    values = data_values(body)
    if values > settings.sync_max_values:
        raise RequestTooLarge(f"the experiments carry {values} numbers; this endpoint takes at most "
                              f"{settings.sync_max_values}; split the experiments over several requests")
    return await run_sync(request, "simulate", body.model_dump(mode="json"))
