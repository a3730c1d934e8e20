import json
from typing import Annotated, Any

from fastapi import APIRouter, Depends, HTTPException, Query, Request
from fastapi.responses import HTMLResponse
from sqlalchemy import and_, select

from greyfit.schemas.design import DesignRequest
from greyfit.schemas.frequency import FrequencyFitRequest
from greyfit.schemas.report import ReportRequest
from greyfit.service.http.deps import client_of, require_api_key
from greyfit.service.http.json_body import StrictJSONRoute
from greyfit.service.http.limits import (
    check_design_limits,
    check_frequency_limits,
    check_limits,
    data_values,
    design_values,
    frequency_values,
)
from greyfit.service.http.problems import PROBLEM
from greyfit.service.http.query import QueryInt
from greyfit.service.http.routes.jobs import JOB_ID, MAX_INDEX
from greyfit.service.http.routes.sync import run_sync, run_sync_request
from greyfit.service.jobs.store import task_requests, tasks
from greyfit.service.settings import Settings

router = APIRouter(prefix="/v1", tags=["report"], dependencies=[Depends(require_api_key)],
                   route_class=StrictJSONRoute)

Responses = dict[int | str, dict[str, Any]]   # APIRouter's `responses`
HTML: Responses = {200: {"content": {"text/html": {}}, "description": "one self-contained HTML page"}}
NOT_FINISHED: Responses = {409: {
    "description": "the task has no result yet (queued, running, failed or cancelled): wait for it, or report "
                   "another task",
    "content": {PROBLEM: {"schema": {"$ref": "#/components/schemas/Problem"}}}}}


async def _page(request: Request, payload: dict | str) -> HTMLResponse:
    response = await run_sync(request, "report", payload)
    return HTMLResponse(json.loads(bytes(response.body))["html"])


def _check_report(body: ReportRequest, settings: Settings) -> None:
    """The request that comes with a result is simulated again: the fits' limits apply to it."""
    if isinstance(body.request, FrequencyFitRequest):
        check_frequency_limits(body.request, settings, "request.")
    elif isinstance(body.request, DesignRequest):
        check_design_limits(body.request, settings, "request.")
    elif body.request is not None:
        check_limits(body.request, settings, "request.")


def _report_values(body: ReportRequest) -> int:
    if isinstance(body.request, FrequencyFitRequest):
        return frequency_values(body.request)
    if isinstance(body.request, DesignRequest):
        return design_values(body.request)
    return data_values(body.request) if body.request is not None else 0


@router.post("/report", response_class=HTMLResponse, responses=HTML)
async def create_report(body: ReportRequest, request: Request) -> HTMLResponse:
    """The report page of a result (with its request for the measured-vs-simulated figures)."""
    response = await run_sync_request(request, "report", body, check=_check_report, count=_report_values,
                                      elsewhere="Draw it with the command line: greyfit report result.json "
                                                "--request request.json --out DIR")
    return HTMLResponse(json.loads(bytes(response.body))["html"])


@router.get("/jobs/{job_id}/report", response_class=HTMLResponse, responses={**HTML, **NOT_FINISHED})
async def job_report(job_id: Annotated[str, JOB_ID], request: Request,
                     index: Annotated[QueryInt, Query(ge=0, le=MAX_INDEX)] = 0) -> HTMLResponse:
    """The report page of task `index` of a finished job (its stored request supplies the data)."""
    store = request.app.state.store
    if store.get_job(job_id, task_limit=0, client=client_of(request).job_filter) is None:   # or another's
        raise HTTPException(404, f"no job with id '{job_id}'")
    with store.engine.connect() as conn:
        row = conn.execute(select(tasks.c.status, task_requests.c.request, tasks.c.result)
                           .join(task_requests, and_(task_requests.c.job_id == tasks.c.job_id,
                                                     task_requests.c.idx == tasks.c.idx))
                           .where(tasks.c.job_id == job_id, tasks.c.idx == index)).mappings().first()
    if row is None:
        raise HTTPException(404, f"job '{job_id}' has no task {index}")
    if row["status"] != "succeeded" or not row["result"]:
        raise HTTPException(409, f"task {index} of job '{job_id}' is {row['status']}; a report needs its result")
    payload = {"result": json.loads(row["result"]), "request": json.loads(row["request"]),
               "title": f"job {job_id}, task {index}"}
    return await _page(request, payload)
