from fastapi import APIRouter, Request
from fastapi.responses import PlainTextResponse

router = APIRouter(tags=["operations"])


@router.get("/metrics", response_class=PlainTextResponse)
def metrics(request: Request) -> PlainTextResponse:
    """Prometheus metrics: requests, fits by status, fit durations, queue depth."""
    state = request.app.state
    # tasks this server has claimed for its next free workers are waiting too
    waiting = state.store.queue_depth() + len(state.dispatcher.ready)
    text = state.metrics.render(waiting, state.dispatcher.running_count())
    return PlainTextResponse(text, media_type="text/plain; version=0.0.4")
