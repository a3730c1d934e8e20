"""Batch jobs. A job's status is what clients poll, so its answers are made without FastAPI's
second pass over the returned model (dump, validate, dump again), and results go out as the
workers wrote them."""
import hashlib
import json
import re
from datetime import datetime, timezone
from typing import Annotated, Any, Callable, Optional

from fastapi import APIRouter, HTTPException, Path, Query, Request, Response
from fastapi.responses import StreamingResponse
from pydantic import BaseModel

from greyfit.schemas.jobs import JobProgress, JobPublic, JobResults, JobsPublic, JobSummary, TaskError, TaskPublic
from greyfit.service.http.backpressure import check_queue_room
from greyfit.service.http.deps import client_of
from greyfit.service.http.json_body import StrictJSONRoute, request_texts
from greyfit.service.http.limits import check_limits
from greyfit.service.http.problems import LimitExceeded
from greyfit.service.http.query import QueryInt
from greyfit.service.jobs.store import IdempotencyKeyReused, status_of_counts

router = APIRouter(prefix="/v1/jobs", tags=["jobs"], route_class=StrictJSONRoute)

MAX_OFFSET = 2 ** 31 - 1   # databases take 64-bit offsets at most; nobody pages this far
MAX_INDEX = 2 ** 31 - 1    # PostgreSQL's INTEGER: a larger task index cannot exist and must not reach it
# job ids are uuid4 text: anything else (a NUL byte, a megabyte) is a 422 before it reaches the database
JOB_ID = Path(description="the job's id, as POST returned it", max_length=36, pattern=r"^[0-9A-Za-z-]+$")


def job_summary(entry: dict[str, Any]) -> JobSummary:
    """A job's status, progress and times, from its task counts by status (store.list_jobs, store.get_job)."""
    job, counts = entry["job"], entry["counts"]
    done = sum(counts.get(s, 0) for s in ("succeeded", "failed", "cancelled"))
    return JobSummary(
        id=job["id"], kind=job["kind"], label=job["label"], status=status_of_counts(bool(job["cancelled"]), counts),
        progress=JobProgress(done=done, total=job["total"], succeeded=counts.get("succeeded", 0),
                             failed=counts.get("failed", 0)),
        created_at=datetime.fromtimestamp(job["created_at"], timezone.utc), started_at=utc(entry["started_at"]),
        finished_at=utc(entry["finished_at"]) if done == job["total"] else None)


def utc(stamp: Optional[float]) -> Optional[datetime]:
    """The store's Unix time as the RFC 3339 timestamp the public schema has (UTC)."""
    return None if stamp is None else datetime.fromtimestamp(stamp, timezone.utc)


def job_public(record: dict[str, Any]) -> JobPublic:
    """A job's summary with the tasks `store.get_job` read (all of them, or a page)."""
    return JobPublic(**dict(job_summary(record)), tasks=[
        TaskPublic(index=r["idx"], status=r["status"], attempts=r["attempts"], started_at=utc(r["started_at"]),
                   finished_at=utc(r["finished_at"]), error=json.loads(r["error"]) if r["error"] else None)
        for r in record["tasks"]])


def as_json(model: BaseModel, status_code: int = 200, headers: Optional[dict] = None) -> Response:
    """The answer of a route whose `response_model` is the model's own class."""
    return Response(model.model_dump_json(), status_code=status_code, headers=headers, media_type="application/json")


IDEMPOTENCY_KEY = re.compile(r"^[\x21-\x7e]{1,200}$")


def idempotency_of(request: Request, kind: str, texts: list, label: Optional[str]) -> Optional[tuple[str, str]]:
    """(key as stored, fingerprint) of the request's Idempotency-Key header, or None without one.

    The fingerprint covers the kind, the label and each request's JSON text: the same key with the
    same body is the same job (a retry after a lost answer), with another body an error. A key is
    each client's own: a named client's is stored as a digest of its name and the key, so that the
    same key sent by two clients makes two jobs, and neither learns of the other's."""
    key = request.headers.get("idempotency-key")
    if key is None:
        return None
    key = key.strip().strip('"')   # the draft sends it as a structured-field string: "abc"
    if not IDEMPOTENCY_KEY.match(key):
        raise HTTPException(400, "Idempotency-Key must be 1 to 200 printable ASCII characters without spaces")
    # [kind, label] as JSON: no label (null) and the label "None" differ; the requests are JSON texts,
    # which hold no NUL byte, so NUL separates them
    digest = hashlib.sha256(json.dumps([kind, label]).encode())
    for text in texts:
        digest.update(b"\0" + (text if isinstance(text, str) else json.dumps(text, sort_keys=True)).encode())
    owner = client_of(request).owner
    if owner:   # '' (the single key, or no keys): stored as sent, as before clients
        key = "client:" + hashlib.sha256(f"{owner}\0{key}".encode()).hexdigest()
    return key, digest.hexdigest()


def submit_job(request: Request, kind: str, requests: list, label: Optional[str],
               check: Callable = check_limits) -> Response:
    """Store a job of one task per request (each checked against this server's limits by `check`)."""
    state = request.app.state
    settings = state.settings
    if len(requests) > settings.max_batch_requests:
        raise LimitExceeded("requests", f"{len(requests)} requests, the limit is {settings.max_batch_requests}; "
                            "split the batch")
    for i, req in enumerate(requests):
        check(req, settings, prefix=f"requests[{i}].")
    check_queue_room(request, len(requests))
    texts = request_texts(request, requests)
    try:
        job_id = state.store.create_job(kind, texts, label, idempotency_of(request, kind, texts, label),
                                        client=client_of(request).owner)
    except IdempotencyKeyReused:
        raise HTTPException(422, f"Idempotency-Key '{request.headers['idempotency-key'].strip().strip(chr(34))}' "
                            "was first sent with another body; a retry must send the same body, a new job a new "
                            "key") from None
    state.dispatcher.wake()
    return as_json(job_public(state.store.get_job(job_id)), 202, {"Location": f"/v1/jobs/{job_id}"})


@router.get("", response_model=JobsPublic)
def list_jobs(request: Request, offset: Annotated[QueryInt, Query(ge=0, le=MAX_OFFSET)] = 0,
              limit: Annotated[QueryInt, Query(ge=1, le=200)] = 20) -> Response:
    """Jobs, newest first, with paging: each job's status and progress, not its tasks (GET /v1/jobs/{id})."""
    entries, count = request.app.state.store.list_jobs(offset, limit, client_of(request).job_filter)
    return as_json(JobsPublic(data=[job_summary(e) for e in entries], count=count))


def _record(request: Request, job_id: str, task_offset: int = 0, task_limit: Optional[int] = None) -> dict:
    """The job (its task page) if it is the caller's; 404 if there is none, or it is another client's."""
    record = request.app.state.store.get_job(job_id, task_offset, task_limit, client_of(request).job_filter)
    if record is None:
        raise HTTPException(404, f"no job with id '{job_id}'")
    return record


# (in Annotated, not as the default: FastAPI then keeps QueryInt's validator)
TASK_OFFSET = Query(ge=0, le=MAX_INDEX, description="the first task listed (paging of `tasks`)")
TASK_LIMIT = Query(ge=1, le=MAX_INDEX, description="how many tasks to list at most (default: all)")


def _tasks_that_fit(public: JobPublic, size: int, limit: int) -> int:
    """How many tasks a page may list to stay within `limit` bytes, were each as large as the largest now."""
    sizes = [len(t.model_dump_json()) + 1 for t in public.tasks]
    rest = size - sum(sizes)
    return max(1, (limit - rest) // max(sizes, default=1))


@router.get("/{job_id}", response_model=JobPublic)
def get_job(job_id: Annotated[str, JOB_ID], request: Request, task_offset: Annotated[QueryInt, TASK_OFFSET] = 0,
            task_limit: Annotated[Optional[QueryInt], TASK_LIMIT] = None) -> Response:
    """Status, progress and per-task status of a job (`task_offset`, `task_limit` page the tasks)."""
    public = job_public(_record(request, job_id, task_offset, task_limit))   # the page only, read in SQL
    body = public.model_dump_json()
    limit = request.app.state.settings.max_answer_bytes
    if len(body) > limit:   # a bounded answer, and the way to the rest of it
        raise LimitExceeded("task_limit", f"the job's status with {len(public.tasks)} tasks would be {len(body)} "
                            f"bytes, more than this server answers at once ({limit}, GREYFIT_MAX_ANSWER_BYTES): "
                            f"page the tasks with task_offset and task_limit (e.g. task_offset={task_offset}&"
                            f"task_limit={_tasks_that_fit(public, len(body), limit)}); the results come from "
                            f"GET /v1/jobs/{job_id}/results, streamed and paged with offset and limit")
    return Response(body, media_type="application/json")


RESULT_OFFSET = Query(ge=0, le=MAX_INDEX, description="the first task whose result is returned (paging)")
RESULT_LIMIT = Query(ge=1, le=MAX_INDEX, description="how many results at most (default: all)")


@router.get("/{job_id}/results", response_model=JobResults)
def get_results(job_id: Annotated[str, JOB_ID], request: Request, offset: Annotated[QueryInt, RESULT_OFFSET] = 0,
                limit: Annotated[Optional[QueryInt], RESULT_LIMIT] = None) -> Response:
    """One entry per request, in order; failed tasks carry their error, unfinished ones no result yet.
    Streamed from the job store a few results at a time; `offset` and `limit` page them."""
    status = job_summary(_record(request, job_id, task_limit=0)).status   # from counts: no task rows read
    pages = request.app.state.store.result_pages(job_id, offset, limit)

    def body():
        yield f'{{"id":{json.dumps(job_id)},"status":"{status}","results":['
        for n, (idx, task_status, result, error) in enumerate(pages):
            # the result as its worker wrote it, a slice at a time; an error through TaskError, which
            # leaves out what is not for the caller (the traceback of an internal error)
            error_json = TaskError.model_validate_json(error).model_dump_json() if error else "null"
            yield f'{"," if n else ""}{{"index":{idx},"status":{json.dumps(task_status)},"result":'
            yield from result if result is not None else ("null",)
            yield f',"error":{error_json}}}'
        yield "]}"

    return StreamingResponse(body(), media_type="application/json")


@router.delete("/{job_id}", response_model=JobPublic)
def cancel_job(job_id: Annotated[str, JOB_ID], request: Request) -> Response:
    """Cancel: queued tasks are dropped, running ones stopped; finished results are kept."""
    _record(request, job_id)
    request.app.state.store.cancel(job_id)
    request.app.state.dispatcher.wake()
    return as_json(job_public(_record(request, job_id)))
