from fastapi import APIRouter, Depends, Request
from fastapi.responses import PlainTextResponse

from service.deps import require_api_key

router = APIRouter(tags=["operations"], dependencies=[Depends(require_api_key)])


@router.get("/metrics", response_class=PlainTextResponse)
def metrics(request: Request) -> PlainTextResponse:
    """Prometheus metrics: requests, fits by status, fit durations, queue depth."""
    state = request.app.state
    text = state.metrics.render(state.store.queue_depth(), state.dispatcher.running_count())
    return PlainTextResponse(text, media_type="text/plain; version=0.0.4")
