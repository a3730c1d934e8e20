from fastapi import APIRouter, Request

from greyfit.service.problems import Problem, problem
from greyfit.service.store import StoreUnavailable

router = APIRouter(tags=["health"])


@router.get("/healthz")
def healthz() -> dict:
    """Liveness: the process answers."""
    return {"status": "ok"}


@router.get("/readyz", responses={503: {"model": Problem, "description": "not ready: the detail says why"}})
def readyz(request: Request):
    """Readiness: the job store takes a write and the dispatcher runs."""
    state = request.app.state
    try:
        state.store.check_writable(state.dispatcher.owner)
    except StoreUnavailable as exc:   # report, do not raise: this is what a probe reads
        return problem(503, "Not ready", str(exc), "not-ready")
    if not state.dispatcher.is_alive():
        return problem(503, "Not ready", "the dispatcher thread is not running", "not-ready")
    return {"status": "ready", "executor": state.settings.executor}
