from fastapi import APIRouter, Request

from greyfit.schemas.health import Health, Readiness
from greyfit.service.http.deps import carries_api_key
from greyfit.service.http.problems import Problem, problem
from greyfit.service.jobs.store import StoreUnavailable

router = APIRouter(tags=["health"])


@router.get("/healthz", response_model=Health)
def healthz() -> dict:
    """Liveness: the process answers."""
    return {"status": "ok"}


@router.get("/readyz", response_model=Readiness,
            responses={503: {"model": Problem, "description": "not ready: the detail says why"}})
def readyz(request: Request):
    """Readiness: the job store takes a write and the dispatcher runs."""
    state = request.app.state
    try:
        state.store.check_writable(state.dispatcher.owner)
    except StoreUnavailable as exc:   # report, do not raise: this is what a probe reads
        # the database's own message names files, hosts and ports: only for callers with the key
        detail = str(exc) if carries_api_key(request) else exc.public
        answer = problem(503, "Not ready", detail, "not-ready")
        answer.headers["Retry-After"] = str(state.settings.retry_after_seconds)
        return answer
    reason = "the dispatcher thread is not running" if not state.dispatcher.is_alive() else \
        state.dispatcher.executor.unready()   # e.g. a Dask cluster without scheduler or workers: nothing would run
    if reason is not None:
        answer = problem(503, "Not ready", reason, "not-ready")
        answer.headers["Retry-After"] = str(state.settings.retry_after_seconds)
        return answer
    return {"status": "ready", "executor": state.settings.executor}
