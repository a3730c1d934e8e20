import asyncio

from fastapi import APIRouter, Depends, HTTPException, Request

from schemas.fit import FitRequest, FitResult
from service.deps import require_api_key
from service.limits import check_limits, data_values
from service.problems import RequestTooLarge
from service.runner import outcome_or_raise

router = APIRouter(prefix="/v1", tags=["fits"], dependencies=[Depends(require_api_key)])


@router.post("/fits", response_model=FitResult)
async def create_fit(body: FitRequest, request: Request) -> FitResult:
    """Run one fit synchronously (small problems); larger ones belong in /v1/jobs."""
    settings = request.app.state.settings
    check_limits(body, settings)
    values = data_values(body)
    if values > settings.sync_max_values:
        raise RequestTooLarge(f"the experiments carry {values} numbers; synchronous fits take at most "
                              f"{settings.sync_max_values}. Submit it as a batch job: POST /v1/jobs "
                              '{"requests": [<this body>]}')
    return await run_sync(request, "fit", body.model_dump(mode="json"))


async def run_sync(request: Request, kind: str, payload: dict):
    state = request.app.state
    fut = state.dispatcher.submit_sync(kind, payload)
    try:
        # shield: a cancelled wait must not cancel the future before the dispatcher can stop the worker
        outcome = await asyncio.wait_for(asyncio.shield(asyncio.wrap_future(fut)),
                                         timeout=state.settings.task_wall_seconds + 30)
    except asyncio.TimeoutError:
        state.dispatcher.cancel_sync(fut)
        raise HTTPException(504, "the fit did not finish in time; submit it as a job") from None
    except asyncio.CancelledError:   # the client went away: free the worker
        state.dispatcher.cancel_sync(fut)
        raise
    return outcome_or_raise(outcome)
