from fastapi import APIRouter, Request
from fastapi.responses import PlainTextResponse

from greyfit.service.metrics import CONTENT_TYPE

router = APIRouter(tags=["operations"])


@router.get("/metrics", response_class=PlainTextResponse)
def metrics(request: Request) -> PlainTextResponse:
    """Prometheus metrics: requests, fits, queues, running tasks, workers lost, store errors, the process."""
    return PlainTextResponse(request.app.state.metrics.render(), media_type=CONTENT_TYPE)
