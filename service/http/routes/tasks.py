"""The synchronous and batch-job routes of every task kind that asks for them (service/task_kinds.py).

Each kind gets POST `sync_path` (answered by a worker while the client waits, within the size and
time limits) and POST `jobs_path` (a stored job of one task per request). Written once here, so a
new kind needs no route code of its own.
"""
from __future__ import annotations

from fastapi import APIRouter, Request, Response

from greyfit.schemas.jobs import JobPublic
from greyfit.service.http.json_body import StrictJSONRoute
from greyfit.service.http.routes.jobs import submit_job
from greyfit.service.http.routes.sync import run_sync_request
from greyfit.service.task_kinds import KINDS, TaskKind


def _sync_endpoint(kind: TaskKind):
    check, count = kind.check(), kind.count()

    async def endpoint(body, request: Request):
        return await run_sync_request(request, kind.name, body, check=check, count=count,
                                      elsewhere=kind.elsewhere)

    endpoint.__annotations__ = {"body": kind.request_schema(), "request": Request}
    endpoint.__name__ = endpoint.__qualname__ = kind.operation or f"create_{kind.name}"
    endpoint.__doc__ = kind.summary
    return endpoint


def _job_endpoint(kind: TaskKind):
    check = kind.check()

    def endpoint(body, request: Request) -> Response:
        return submit_job(request, kind.name, body.requests, body.label, check=check)

    endpoint.__annotations__ = {"body": kind.job_schema(), "request": Request, "return": Response}
    endpoint.__name__ = endpoint.__qualname__ = kind.job_operation or f"create_{kind.name}_job"
    endpoint.__doc__ = kind.job_summary
    return endpoint


def task_routers() -> list[APIRouter]:
    """One router per kind whose routes are generated."""
    routers = []
    for kind in KINDS.values():
        if not kind.generate:
            continue
        router = APIRouter(route_class=StrictJSONRoute)
        if kind.sync_path:
            router.add_api_route(kind.sync_path, _sync_endpoint(kind), methods=["POST"], tags=[kind.tag],
                                 response_model=kind.result_schema())
        if kind.jobs_path:   # fits' jobs are the jobs resource's own POST; other kinds' sit with their kind
            router.add_api_route(kind.jobs_path, _job_endpoint(kind), methods=["POST"],
                                 tags=["jobs"] if kind.jobs_path == "/v1/jobs" else [kind.tag],
                                 response_model=JobPublic, status_code=202)
        routers.append(router)
    return routers
