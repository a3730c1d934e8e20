from fastapi import APIRouter, Request, Response
from pydantic import BaseModel, ConfigDict, Field
from typing import Optional

from greyfit.schemas.discovery import DiscoverRequest, DiscoveryResult
from greyfit.schemas.jobs import JobPublic
from greyfit.service.json_body import StrictJSONRoute
from greyfit.service.limits import check_limits, data_values
from greyfit.service.routes.sync import run_sync_request
from greyfit.service.routes.jobs import submit_job

router = APIRouter(prefix="/v1", tags=["discovery"], route_class=StrictJSONRoute)


class DiscoverJobCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")

    requests: list[DiscoverRequest] = Field(min_length=1)
    label: Optional[str] = Field(default=None, max_length=200)


@router.post("/discover", response_model=DiscoveryResult)
async def create_discovery(body: DiscoverRequest, request: Request):
    """Fit, trace the residual to a missing physical effect, add it, refit: before/after and evidence."""
    return await run_sync_request(request, "discover", body, check=check_limits, count=data_values,
                                  elsewhere="Submit it as a job: POST /v1/discover/jobs")


@router.post("/discover/jobs", response_model=JobPublic, status_code=202)
def create_discovery_job(body: DiscoverJobCreate, request: Request) -> Response:
    """Discovery requests as a batch job; results at /v1/jobs/{id}/results."""
    return submit_job(request, "discover", body.requests, body.label)
