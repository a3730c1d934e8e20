from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse
from sqlalchemy import text

router = APIRouter(tags=["health"])


@router.get("/healthz")
def healthz() -> dict:
    """Liveness: the process answers."""
    return {"status": "ok"}


@router.get("/readyz")
def readyz(request: Request):
    """Readiness: the job store answers and the dispatcher runs."""
    state = request.app.state
    try:
        with state.store.engine.connect() as conn:
            conn.execute(text("SELECT 1"))
    except Exception as exc:  # report, do not raise: this is what a probe reads
        return JSONResponse({"status": "unavailable", "detail": f"job store: {exc}"}, status_code=503)
    thread = state.dispatcher._thread
    if thread is None or not thread.is_alive():
        return JSONResponse({"status": "unavailable", "detail": "dispatcher not running"}, status_code=503)
    return {"status": "ready", "executor": state.settings.executor}
