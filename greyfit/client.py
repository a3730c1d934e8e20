"""A small typed client of the greyfit HTTP service.

    from greyfit.client import Client
    client = Client("http://127.0.0.1:8000", api_key=None)
    result = client.fit(request)            # a FitRequest (or its dict) -> FitResult

It uses only the standard library (urllib): calling greyfit must not add an HTTP stack to the
caller's environment, and JSON over HTTP/1.1 needs nothing more. Requests and results are the
service's own pydantic schemas; a job's results come typed by the job's kind (`JobOutcomes`).

A server at capacity answers 503, one past its rate limit 429, both with `Retry-After`: the client
waits that long and sends the request again, at most `max_retries` times and `max_retry_wait`
seconds in all (a wait that would pass that budget is not begun: the error is raised at once).
Both are safe to retry: the server refused the request before doing any of its work.
"""
from __future__ import annotations

import email.utils
import json
import time
import urllib.error
import urllib.request
import uuid
from typing import Any, Generic, Optional, Sequence, TypeVar, Union

from pydantic import BaseModel

from greyfit.schemas.discovery import DiscoverRequest, DiscoveryResult
from greyfit.schemas.fit import FitRequest, FitResult
from greyfit.schemas.frequency import FrequencyFitRequest
from greyfit.schemas.jobs import JobPublic, JobsPublic, JobStatus, TaskError, TaskStatus
from greyfit.schemas.simulate import SimulateRequest, SimulateResult
from greyfit.service.task_kinds import JOB_KINDS, KINDS

FINISHED = ("succeeded", "failed", "cancelled")
RETRY_STATUSES = (429, 503)
# a 503 or 429 without Retry-After (a proxy's): wait this long, doubling each time
FALLBACK_WAIT = 1.0

R = TypeVar("R", bound=BaseModel)


class JobOutcome(BaseModel, Generic[R]):
    """One request of a job: its result (the result schema of the job's kind: FitResult,
    DiscoveryResult, ...) once it succeeded, its error once it failed."""

    index: int
    status: TaskStatus
    result: Optional[R] = None
    error: Optional[TaskError] = None


class JobOutcomes(BaseModel, Generic[R]):
    """GET /v1/jobs/{id}/results with each result typed."""

    id: str
    status: JobStatus
    results: list[JobOutcome[R]]


class GreyfitError(Exception):
    """An HTTP error answered by the service; `problem` is its problem+json body (when there is one)."""

    def __init__(self, status: int, problem: dict[str, Any], retry_after: Optional[float] = None):
        self.status, self.problem, self.retry_after = status, problem, retry_after
        super().__init__(f"{status} {problem.get('title', '')}: {problem.get('detail', problem)}")

    @property
    def request_id(self) -> Optional[str]:
        """The id the server's log lines about this request carry."""
        return self.problem.get("request_id")


class Client:
    """The service's routes as methods.

    Parameters
    ----------
    base_url : e.g. "http://127.0.0.1:8000"
    api_key : sent as 'Authorization: Bearer <key>' when the server sets GREYFIT_API_KEY
    timeout : seconds to wait for one answer (a synchronous fit's included)
    max_retries : how often a 429 or 503 is retried (0: never)
    max_retry_wait : seconds of Retry-After waits in all, per call
    """

    def __init__(self, base_url: str, api_key: Optional[str] = None, timeout: float = 600.0,
                 max_retries: int = 5, max_retry_wait: float = 120.0):
        self.base_url = base_url.rstrip("/")
        self.api_key = api_key
        self.timeout = timeout
        self.max_retries, self.max_retry_wait = max_retries, max_retry_wait
        self.last_retries: list[tuple[int, float]] = []   # (status, seconds waited) of the last call

    # --- plumbing --------------------------------------------------------------------------------
    def _request(self, method: str, path: str, body: Any = None,
                 headers: Optional[dict[str, str]] = None) -> tuple[int, bytes]:
        """One call, retried on 429/503 as the server's Retry-After says, within the bounds."""
        self.last_retries = []
        waited = 0.0
        while True:
            try:
                return self._send(method, path, body, headers)
            except GreyfitError as exc:
                wait = self._retry_wait(exc, len(self.last_retries), waited)
                if wait is None:
                    raise
                status = exc.status
            time.sleep(wait)
            waited += wait
            self.last_retries.append((status, wait))

    def _retry_wait(self, exc: GreyfitError, retries: int, waited: float) -> Optional[float]:
        """Seconds to wait before retrying, or None to give up."""
        if exc.status not in RETRY_STATUSES or retries >= self.max_retries:
            return None
        wait = exc.retry_after if exc.retry_after is not None else FALLBACK_WAIT * 2 ** retries
        return wait if waited + wait <= self.max_retry_wait else None

    def _send(self, method: str, path: str, body: Any = None,
              extra_headers: Optional[dict[str, str]] = None) -> tuple[int, bytes]:
        data = None
        headers = {"accept": "application/json", **(extra_headers or {})}
        if body is not None:
            # what was set only: a fit chooses what the request leaves to it (substeps, interpolation)
            data = (body.model_dump_json(exclude_unset=True) if isinstance(body, BaseModel)
                    else json.dumps(body)).encode()
            headers["content-type"] = "application/json"
        if self.api_key:
            headers["authorization"] = f"Bearer {self.api_key}"
        req = urllib.request.Request(self.base_url + path, data=data, headers=headers, method=method)
        try:
            with urllib.request.urlopen(req, timeout=self.timeout) as resp:
                return resp.status, resp.read()
        except urllib.error.HTTPError as exc:
            raw = exc.read()
            try:
                problem = json.loads(raw)
            except ValueError:
                problem = {"detail": raw.decode(errors="replace")}
            raise GreyfitError(exc.code, problem if isinstance(problem, dict) else {"detail": problem},
                               _retry_after(exc.headers.get("Retry-After"))) from None

    def _json(self, method: str, path: str, body: Any = None, headers: Optional[dict[str, str]] = None) -> Any:
        return json.loads(self._request(method, path, body, headers)[1])

    @staticmethod
    def _as(model: type[BaseModel], value: Union[BaseModel, dict]) -> BaseModel:
        return value if isinstance(value, model) else model.model_validate(value)

    # --- the API ---------------------------------------------------------------------------------
    def fit(self, request: Union[FitRequest, dict]) -> FitResult:
        """One synchronous fit (POST /v1/fits)."""
        return FitResult.model_validate(self._json("POST", "/v1/fits", self._as(FitRequest, request)))

    def discover(self, request: Union[DiscoverRequest, dict]) -> DiscoveryResult:
        """Fit, find missing effects, refit (POST /v1/discover)."""
        return DiscoveryResult.model_validate(
            self._json("POST", "/v1/discover", self._as(DiscoverRequest, request)))

    def simulate(self, request: Union[SimulateRequest, dict]) -> SimulateResult:
        """Simulate a model with given parameters or a previous result (POST /v1/simulate)."""
        return SimulateResult.model_validate(
            self._json("POST", "/v1/simulate", self._as(SimulateRequest, request)))

    def submit_job(self, requests: Sequence[Union[FitRequest, DiscoverRequest, FrequencyFitRequest, dict]],
                   label: Optional[str] = None, kind: str = "fit",
                   idempotency_key: Optional[str] = None) -> JobPublic:
        """A batch job of fits (kind 'fit'), discoveries ('discover') or frequency-response fits
        ('frequency_fit'); returns at once.

        Sent with an Idempotency-Key (a new random one unless given), the same on every retry: a
        503 answered after the job was stored (a proxy's, a lost answer) and retried gives that job,
        not a second one."""
        if kind not in JOB_KINDS:
            raise ValueError(f"kind must be one of {list(JOB_KINDS)}")
        schema, path = KINDS[kind].request_schema(), KINDS[kind].jobs_path
        body: dict[str, Any] = {"requests": [self._as(schema, r).model_dump(mode="json", exclude_unset=True)
                                             for r in requests]}
        if label is not None:
            body["label"] = label
        key = idempotency_key or uuid.uuid4().hex
        return JobPublic.model_validate(self._json("POST", str(path), body, {"Idempotency-Key": key}))

    def frequency_fit(self, request: Union[FrequencyFitRequest, dict]) -> FitResult:
        """One synchronous frequency-response fit (POST /v1/frequency-fits)."""
        return FitResult.model_validate(
            self._json("POST", "/v1/frequency-fits", self._as(FrequencyFitRequest, request)))

    def job(self, job_id: str) -> JobPublic:
        """Status, progress and per-task status of a job (GET /v1/jobs/{id})."""
        return JobPublic.model_validate(self._json("GET", f"/v1/jobs/{job_id}"))

    def list_jobs(self, offset: int = 0, limit: int = 20) -> JobsPublic:
        """Jobs, newest first (GET /v1/jobs); `count` is the number of all jobs."""
        return JobsPublic.model_validate(self._json("GET", f"/v1/jobs?offset={int(offset)}&limit={int(limit)}"))

    def cancel(self, job_id: str) -> JobPublic:
        """Cancel a job (DELETE /v1/jobs/{id}): queued tasks dropped, running ones stopped, finished
        results kept."""
        return JobPublic.model_validate(self._json("DELETE", f"/v1/jobs/{job_id}"))

    def wait(self, job_id: str, timeout: float = 600.0, poll: float = 0.2) -> JobPublic:
        """Poll until the job is succeeded, failed or cancelled; TimeoutError after `timeout` s."""
        deadline = time.monotonic() + timeout
        while True:
            job = self.job(job_id)
            if job.status in FINISHED:
                return job
            if time.monotonic() > deadline:
                raise TimeoutError(f"job {job_id} is still {job.status} after {timeout} s")
            time.sleep(poll)

    def results(self, job_id: str, kind: Optional[str] = None) -> JobOutcomes:
        """One entry per request (GET /v1/jobs/{id}/results), each `result` a FitResult (jobs of kind
        'fit' and 'frequency_fit') or a DiscoveryResult ('discover'). Without `kind`, the job's is
        asked for first."""
        kind = kind or self.job(job_id).kind
        # the result schema is known at run time only (the task kinds' table)
        outcomes = JobOutcomes[KINDS[kind].result_schema()]  # type: ignore[misc,valid-type]
        return outcomes.model_validate(self._json("GET", f"/v1/jobs/{job_id}/results"))

    def report(self, result: Union[FitResult, DiscoveryResult, dict],
               request: Union[FitRequest, DiscoverRequest, dict, None] = None) -> str:
        """The HTML report page of a result (POST /v1/report)."""
        body = {"result": result.model_dump(mode="json") if isinstance(result, BaseModel) else result}
        if request is not None:
            body["request"] = request.model_dump(mode="json", exclude_unset=True) if isinstance(request, BaseModel) \
                else request
        return self._request("POST", "/v1/report", body)[1].decode()

    def job_report(self, job_id: str, index: int = 0) -> str:
        """The HTML report page of one request of a job (GET /v1/jobs/{id}/report)."""
        return self._request("GET", f"/v1/jobs/{job_id}/report?index={index}")[1].decode()


def _retry_after(value: Optional[str]) -> Optional[float]:
    """Retry-After in seconds: delay-seconds or an HTTP date (RFC 9110 10.2.3); None if absent or unreadable."""
    if not value:
        return None
    value = value.strip()
    if value.isdigit():
        return float(value)
    try:
        when = email.utils.parsedate_to_datetime(value)
    except (TypeError, ValueError):
        return None
    return max(0.0, when.timestamp() - time.time())
