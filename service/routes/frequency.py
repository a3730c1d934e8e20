from fastapi import APIRouter, Request, Response

from greyfit.schemas.fit import FitResult
from greyfit.schemas.frequency import FrequencyFitRequest
from greyfit.schemas.jobs import FrequencyJobCreate, JobPublic
from greyfit.service.json_body import StrictJSONRoute
from greyfit.service.limits import check_frequency_limits, frequency_values
from greyfit.service.routes.jobs import submit_job
from greyfit.service.routes.sync import run_sync_request

router = APIRouter(prefix="/v1", tags=["frequency fits"], route_class=StrictJSONRoute)


@router.post("/frequency-fits", response_model=FitResult)
async def create_frequency_fit(body: FrequencyFitRequest, request: Request) -> FitResult:
    """Fit a transfer-function model (optionally in a known feedback loop) to frequency responses."""
    return await run_sync_request(
        request, "frequency_fit", body, check=check_frequency_limits, count=frequency_values,
        elsewhere="Decimate the sine-test records, or submit it as a job: POST /v1/frequency-fits/jobs")


@router.post("/frequency-fits/jobs", response_model=JobPublic, status_code=202)
def create_frequency_job(body: FrequencyJobCreate, request: Request) -> Response:
    """Frequency-response fits as a batch job; results at /v1/jobs/{id}/results."""
    return submit_job(request, "frequency_fit", body.requests, body.label, check=check_frequency_limits)
