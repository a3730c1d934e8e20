from fastapi import APIRouter, Depends, Request

from schemas.fit import FitResult
from schemas.frequency import FrequencyFitRequest
from service.deps import require_api_key
from service.problems import LimitExceeded, RequestTooLarge
from service.routes.fits import run_sync

router = APIRouter(prefix="/v1", tags=["frequency fits"], dependencies=[Depends(require_api_key)])


def frequency_values(body: FrequencyFitRequest) -> int:
    """How many numbers the data carry (the synchronous size measure)."""
    total = 0
    for d in body.data:
        total += 3 * len(d.omega or [])
        total += sum(3 * len(t.time) for t in d.sine_tests or [])
    return total


@router.post("/frequency-fits", response_model=FitResult)
async def create_frequency_fit(body: FrequencyFitRequest, request: Request) -> FitResult:
    """Fit a transfer-function model (optionally in a known feedback loop) to frequency responses."""
    settings = request.app.state.settings
    if len(body.model.parameters) > settings.max_parameters:
        raise LimitExceeded("model.parameters", f"{len(body.model.parameters)} parameters, the limit is "
                            f"{settings.max_parameters}")
    values = frequency_values(body)
    if values > settings.sync_max_values:
        raise RequestTooLarge(f"the data carry {values} numbers; synchronous fits take at most "
                              f"{settings.sync_max_values}: decimate the sine-test records")
    return await run_sync(request, "frequency_fit", body.model_dump(mode="json"))
