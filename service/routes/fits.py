from fastapi import APIRouter, Request

from greyfit.schemas.fit import FitRequest, FitResult
from greyfit.service.json_body import StrictJSONRoute
from greyfit.service.limits import check_limits, data_values
from greyfit.service.routes.sync import run_sync_request

router = APIRouter(prefix="/v1", tags=["fits"], route_class=StrictJSONRoute)


@router.post("/fits", response_model=FitResult)
async def create_fit(body: FitRequest, request: Request) -> FitResult:
    """Run one fit synchronously (small problems); larger ones belong in /v1/jobs."""
    return await run_sync_request(request, "fit", body, check=check_limits, count=data_values, elsewhere=(
        'Submit it as a batch job: POST /v1/jobs {"requests": [<this body>]}'))
