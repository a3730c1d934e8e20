from fastapi import APIRouter, Request

from greyfit.schemas.simulate import SimulateRequest, SimulateResult
from greyfit.service.http.json_body import StrictJSONRoute
from greyfit.service.http.limits import check_simulate_limits, data_values
from greyfit.service.http.routes.sync import run_sync_request

router = APIRouter(prefix="/v1", tags=["simulate"], route_class=StrictJSONRoute)


@router.post("/simulate", response_model=SimulateResult)
async def create_simulation(body: SimulateRequest, request: Request):
    """Simulate a model (parameters given, or from a previous fit/discovery result) on experiments."""
    return await run_sync_request(request, "simulate", body, check=check_simulate_limits, count=data_values,
                                  elsewhere="Split the experiments over several requests.")
