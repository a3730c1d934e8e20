"""A typed client of the greyfit HTTP service, on httpx: `Client` and its async twin `AsyncClient`.

    from greyfit.client import Client
    with Client("http://127.0.0.1:8000") as client:
        result = client.fit(request)            # a FitRequest (or its dict) -> FitResult

One client holds one connection pool (HTTP/1.1 keep-alive): a batch of calls reuses its connections.
Requests and results are the service's own pydantic schemas; a job's results come typed by the
job's kind (`JobOutcomes`). A dict that is not a valid request is refused before it is sent, with
the service's own words (`InvalidRequest`, a 422 `GreyfitError` naming each field as the service
and the CLI name it).

Retries. A server at capacity answers 503, one past its rate limit 429, both with `Retry-After`: the
client waits that long and sends the request again. A connection refused, reset or closed before
the answer (a server restarting, a proxy dropping an idle connection) is retried too, after a
backoff (0.25 s doubling, at most 5 s, each wait drawn between half and all of it so that the
clients of a restarted server do not all come back at once). Both are bounded: at most
`max_retries` retries and `max_retry_wait` seconds of waiting per call (a wait that would pass that
budget is not begun: the error is raised at once). Every call of this client is safe to send again:
reads and cancels are idempotent, a synchronous fit or report stores nothing, and a job is created
with an `Idempotency-Key` (the same on every retry), so a job whose answer was lost is returned, not
made twice. A call that timed out is not retried: the timeout is the caller's budget.
"""
from __future__ import annotations

import asyncio
import email.utils
import json
import random
import time
import uuid
from dataclasses import dataclass, field
from typing import Any, Callable, Generic, Optional, Sequence, TypeVar, Union

import httpx
from pydantic import BaseModel, ValidationError

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
# a connection refused or lost: wait this long, doubling up to the cap (jittered, see the docstring)
CONNECT_WAIT, CONNECT_WAIT_CAP = 0.25, 5.0
# never sent (safe for any call), and sent but unanswered (safe for calls that may be sent twice)
NOT_SENT = (httpx.ConnectError, httpx.ConnectTimeout, httpx.PoolTimeout)
UNANSWERED = (httpx.RemoteProtocolError, httpx.ReadError, httpx.WriteError)

R = TypeVar("R", bound=BaseModel)
Request = Union[FitRequest, DiscoverRequest, FrequencyFitRequest, SimulateRequest, dict]


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

    @property
    def errors(self) -> list[dict[str, str]]:
        """The validation errors of a 422, each {"loc": "experiments[0].time", "msg": ...}."""
        return list(self.problem.get("errors") or [])


class InvalidRequest(GreyfitError):
    """A request the client refused before sending it: the 422 the service would have answered,
    its `errors` and text the service's (and the CLI's)."""


class ServiceUnreachable(ConnectionError):
    """The service could not be reached (refused, reset, closed) within the retries allowed."""


def invalid_request(exc: ValidationError) -> InvalidRequest:
    """The service's 422 for a request that failed validation here (service.http.problems words it alike)."""
    from greyfit.service.http.error_text import describe, request_model
    errors = describe(exc.errors(include_url=False, include_input=False, include_context=False),
                      request_model(exc.title))
    detail = "; ".join(f"{e['loc']}: {e['msg']}" for e in errors[:5])
    return InvalidRequest(422, {"title": "Invalid request", "status": 422, "detail": detail, "errors": errors})


def validated(model: type[BaseModel], value: Union[BaseModel, dict]) -> BaseModel:
    """`value` as `model`: a dict validated as strictly as the service validates a body."""
    if isinstance(value, model):
        return value
    from greyfit.service.http.json_parsing import validate_strict
    try:
        return validate_strict(model, value.model_dump(mode="json", exclude_unset=True)
                               if isinstance(value, BaseModel) else value)
    except ValidationError as exc:
        raise invalid_request(exc) from None


def body_of(value: BaseModel) -> Any:
    # what was set only: a fit chooses what the request leaves to it (substeps, interpolation)
    return value.model_dump(mode="json", exclude_unset=True)


@dataclass
class Call:
    """One HTTP call: what to send, how to read the answer, and whether a lost answer may be sent
    again (every call of this client may; a new one that may not says so here)."""

    method: str
    path: str
    read: Callable[[httpx.Response], Any]
    body: Any = None
    headers: dict[str, str] = field(default_factory=dict)
    resend: bool = True


def _json_as(model: Any) -> Callable[[httpx.Response], Any]:
    return lambda response: model.model_validate(response.json())


def _text(response: httpx.Response) -> str:
    return response.text


def calls_fit(request: Union[FitRequest, dict]) -> Call:
    return Call("POST", "/v1/fits", _json_as(FitResult), body_of(validated(FitRequest, request)))


def calls_discover(request: Union[DiscoverRequest, dict]) -> Call:
    return Call("POST", "/v1/discover", _json_as(DiscoveryResult), body_of(validated(DiscoverRequest, request)))


def calls_simulate(request: Union[SimulateRequest, dict]) -> Call:
    return Call("POST", "/v1/simulate", _json_as(SimulateResult), body_of(validated(SimulateRequest, request)))


def calls_frequency_fit(request: Union[FrequencyFitRequest, dict]) -> Call:
    return Call("POST", "/v1/frequency-fits", _json_as(FitResult),
                body_of(validated(FrequencyFitRequest, request)))


def calls_submit_job(requests: Sequence[Request], label: Optional[str], kind: str,
                     idempotency_key: Optional[str]) -> Call:
    if kind not in JOB_KINDS:
        raise ValueError(f"kind must be one of {list(JOB_KINDS)}")
    schema, path = KINDS[kind].request_schema(), KINDS[kind].jobs_path
    body: dict[str, Any] = {"requests": [body_of(validated(schema, r)) for r in requests]}
    if label is not None:
        body["label"] = label
    return Call("POST", str(path), _json_as(JobPublic), body,
                {"Idempotency-Key": idempotency_key or uuid.uuid4().hex})


def calls_results(job_id: str, kind: str) -> Call:
    # the result schema is known at run time only (the task kinds' table)
    outcomes = JobOutcomes[KINDS[kind].result_schema()]  # type: ignore[misc,valid-type]
    return Call("GET", f"/v1/jobs/{job_id}/results", _json_as(outcomes))


def calls_report(result: Union[FitResult, DiscoveryResult, dict],
                 request: Union[FitRequest, DiscoverRequest, dict, None]) -> Call:
    body = {"result": result.model_dump(mode="json") if isinstance(result, BaseModel) else result}
    if request is not None:
        body["request"] = body_of(request) if isinstance(request, BaseModel) else request
    return Call("POST", "/v1/report", _text, body)


class Retries:
    """The retry budget of one call: how long to wait before the next attempt, or None to give up.
    `done` lists (status or error name, seconds waited) of each retry."""

    def __init__(self, max_retries: int, max_wait: float):
        self.max_retries, self.max_wait = max_retries, max_wait
        self.done: list[tuple[Union[int, str], float]] = []
        self.waited = 0.0

    def after_status(self, exc: GreyfitError) -> Optional[float]:
        if exc.status not in RETRY_STATUSES:
            return None
        n = len(self.done)
        wait = exc.retry_after if exc.retry_after is not None else FALLBACK_WAIT * 2 ** n
        return self._take(exc.status, wait)

    def after_transport(self, exc: httpx.TransportError, call: Call) -> Optional[float]:
        if not (isinstance(exc, NOT_SENT) or (call.resend and isinstance(exc, UNANSWERED))):
            return None
        cap = min(CONNECT_WAIT_CAP, CONNECT_WAIT * 2 ** len(self.done))
        return self._take(type(exc).__name__, cap * random.uniform(0.5, 1.0))

    def _take(self, what: Union[int, str], wait: float) -> Optional[float]:
        if len(self.done) >= self.max_retries or self.waited + wait > self.max_wait:
            return None
        self.done.append((what, wait))
        self.waited += wait
        return wait


class _Base:
    """What the two clients share: settings, headers, answers read into results or errors."""

    def __init__(self, base_url: str, api_key: Optional[str], timeout: float, connect_timeout: float,
                 max_retries: int, max_retry_wait: float):
        self.base_url = base_url.rstrip("/")
        self.api_key = api_key
        self.timeout = timeout
        self.max_retries, self.max_retry_wait = max_retries, max_retry_wait
        self.last_retries: list[tuple[Union[int, str], float]] = []   # (status or error, s waited) of the last call
        self._options: dict[str, Any] = {
            "base_url": self.base_url, "timeout": httpx.Timeout(timeout, connect=connect_timeout),
            "headers": {"accept": "application/json",
                        **({"authorization": f"Bearer {api_key}"} if api_key else {})}}

    def _retries(self) -> Retries:
        retries = Retries(self.max_retries, self.max_retry_wait)
        self.last_retries = retries.done
        return retries

    def _request_args(self, call: Call) -> dict[str, Any]:
        args: dict[str, Any] = {"method": call.method, "url": call.path, "headers": call.headers}
        if call.body is not None:
            # a NaN or ±inf the caller put into a validated request is written as NaN/Infinity (never as
            # null, one sample fewer): the service refuses it at the sample with the same 422 as every path
            args["content"] = json.dumps(call.body, allow_nan=True).encode()
            args["headers"] = {**call.headers, "content-type": "application/json"}
        return args

    @staticmethod
    def _answer(call: Call, response: httpx.Response) -> Any:
        if response.status_code >= 400:
            raise _error_of(response)
        return call.read(response)

    def _wait_after(self, call: Call, retries: Retries, exc: Union[GreyfitError, httpx.TransportError]) -> float:
        """Seconds to wait before sending `call` again after `exc`; raises when it is not retried."""
        if isinstance(exc, GreyfitError):
            wait = retries.after_status(exc)
            if wait is None:
                raise exc
            return wait
        if isinstance(exc, httpx.TimeoutException) and not isinstance(exc, NOT_SENT):
            raise self._timed_out(call, exc) from exc
        wait = retries.after_transport(exc, call)
        if wait is None:
            raise self._unreachable(call, exc) from exc
        return wait

    def _unreachable(self, call: Call, exc: Exception) -> ServiceUnreachable:
        tries = len(self.last_retries)
        return ServiceUnreachable(f"{call.method} {self.base_url}{call.path}: {type(exc).__name__}: {exc} "
                                  f"(after {tries} retr{'y' if tries == 1 else 'ies'})")

    def _timed_out(self, call: Call, exc: Exception) -> TimeoutError:
        return TimeoutError(f"{call.method} {self.base_url}{call.path}: no answer within {self.timeout} s "
                            f"(the client's timeout); {type(exc).__name__}")


class Client(_Base):
    """The service's routes as methods, over one connection pool (`close()` it, or use `with`).

    Parameters
    ----------
    base_url : e.g. "http://127.0.0.1:8000"
    api_key : sent as 'Authorization: Bearer <key>' when the server sets GREYFIT_API_KEY
    timeout : seconds to wait for one answer (a synchronous fit's included)
    connect_timeout : seconds to wait for a connection
    max_retries : how often a 429, a 503 or a lost connection is retried (0: never)
    max_retry_wait : seconds of waits in all, per call
    """

    def __init__(self, base_url: str, api_key: Optional[str] = None, timeout: float = 600.0,
                 max_retries: int = 10, max_retry_wait: float = 120.0, connect_timeout: float = 10.0):
        super().__init__(base_url, api_key, timeout, connect_timeout, max_retries, max_retry_wait)
        self._http = httpx.Client(**self._options)

    def close(self) -> None:
        """Close the pool's connections."""
        self._http.close()

    def __enter__(self) -> Client:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    def _run(self, call: Call) -> Any:
        """One call, retried as the module's docstring says."""
        retries = self._retries()
        while True:
            try:
                return self._answer(call, self._http.request(**self._request_args(call)))
            except (GreyfitError, httpx.TransportError) as exc:
                wait = self._wait_after(call, retries, exc)
            time.sleep(wait)

    def fit(self, request: Union[FitRequest, dict]) -> FitResult:
        """One synchronous fit (POST /v1/fits)."""
        return self._run(calls_fit(request))

    def discover(self, request: Union[DiscoverRequest, dict]) -> DiscoveryResult:
        """Fit, find missing effects, refit (POST /v1/discover)."""
        return self._run(calls_discover(request))

    def simulate(self, request: Union[SimulateRequest, dict]) -> SimulateResult:
        """Simulate a model with given parameters or a previous result (POST /v1/simulate)."""
        return self._run(calls_simulate(request))

    def frequency_fit(self, request: Union[FrequencyFitRequest, dict]) -> FitResult:
        """One synchronous frequency-response fit (POST /v1/frequency-fits)."""
        return self._run(calls_frequency_fit(request))

    def submit_job(self, requests: Sequence[Request], label: Optional[str] = None, kind: str = "fit",
                   idempotency_key: Optional[str] = None) -> JobPublic:
        """A batch job of fits (kind 'fit'), discoveries ('discover') or frequency-response fits
        ('frequency_fit'); returns at once.

        Sent with an Idempotency-Key (a new random one unless given), the same on every retry: a
        job stored before its answer was lost (a restart, a proxy's 503) and retried gives that
        job, not a second one."""
        return self._run(calls_submit_job(requests, label, kind, idempotency_key))

    def job(self, job_id: str) -> JobPublic:
        """Status, progress and per-task status of a job (GET /v1/jobs/{id})."""
        return self._run(Call("GET", f"/v1/jobs/{job_id}", _json_as(JobPublic)))

    def list_jobs(self, offset: int = 0, limit: int = 20) -> JobsPublic:
        """Jobs, newest first (GET /v1/jobs); `count` is the number of all jobs."""
        return self._run(Call("GET", f"/v1/jobs?offset={int(offset)}&limit={int(limit)}", _json_as(JobsPublic)))

    def cancel(self, job_id: str) -> JobPublic:
        """Cancel a job (DELETE /v1/jobs/{id}): queued tasks dropped, running ones stopped, finished
        results kept."""
        return self._run(Call("DELETE", f"/v1/jobs/{job_id}", _json_as(JobPublic)))

    def wait(self, job_id: str, timeout: float = 600.0, poll: float = 0.2) -> JobPublic:
        """Poll until the job is succeeded, failed or cancelled; TimeoutError after `timeout` s."""
        deadline = time.monotonic() + timeout
        while True:
            job = self.job(job_id)
            if _finished(job, job_id, deadline, timeout):
                return job
            time.sleep(poll)

    def results(self, job_id: str, kind: Optional[str] = None) -> JobOutcomes:
        """One entry per request (GET /v1/jobs/{id}/results), each `result` a FitResult (jobs of kind
        'fit' and 'frequency_fit') or a DiscoveryResult ('discover'). Without `kind`, the job's is
        asked for first."""
        return self._run(calls_results(job_id, kind or self.job(job_id).kind))

    def report(self, result: Union[FitResult, DiscoveryResult, dict],
               request: Union[FitRequest, DiscoverRequest, dict, None] = None) -> str:
        """The HTML report page of a result (POST /v1/report)."""
        return self._run(calls_report(result, request))

    def job_report(self, job_id: str, index: int = 0) -> str:
        """The HTML report page of one request of a job (GET /v1/jobs/{id}/report)."""
        return self._run(Call("GET", f"/v1/jobs/{job_id}/report?index={int(index)}", _text))


class AsyncClient(_Base):
    """`Client` for asyncio: the same methods, each a coroutine, over one `httpx.AsyncClient` pool
    (`await aclose()`, or use `async with`). The parameters are `Client`'s."""

    def __init__(self, base_url: str, api_key: Optional[str] = None, timeout: float = 600.0,
                 max_retries: int = 10, max_retry_wait: float = 120.0, connect_timeout: float = 10.0):
        super().__init__(base_url, api_key, timeout, connect_timeout, max_retries, max_retry_wait)
        self._http = httpx.AsyncClient(**self._options)

    async def aclose(self) -> None:
        """Close the pool's connections."""
        await self._http.aclose()

    async def __aenter__(self) -> AsyncClient:
        return self

    async def __aexit__(self, *exc: Any) -> None:
        await self.aclose()

    async def _run(self, call: Call) -> Any:
        """One call, retried as `Client._run` retries it."""
        retries = self._retries()
        while True:
            try:
                return self._answer(call, await self._http.request(**self._request_args(call)))
            except (GreyfitError, httpx.TransportError) as exc:
                wait = self._wait_after(call, retries, exc)
            await asyncio.sleep(wait)

    async def fit(self, request: Union[FitRequest, dict]) -> FitResult:
        """`Client.fit`."""
        return await self._run(calls_fit(request))

    async def discover(self, request: Union[DiscoverRequest, dict]) -> DiscoveryResult:
        """`Client.discover`."""
        return await self._run(calls_discover(request))

    async def simulate(self, request: Union[SimulateRequest, dict]) -> SimulateResult:
        """`Client.simulate`."""
        return await self._run(calls_simulate(request))

    async def frequency_fit(self, request: Union[FrequencyFitRequest, dict]) -> FitResult:
        """`Client.frequency_fit`."""
        return await self._run(calls_frequency_fit(request))

    async def submit_job(self, requests: Sequence[Request], label: Optional[str] = None, kind: str = "fit",
                         idempotency_key: Optional[str] = None) -> JobPublic:
        """`Client.submit_job` (with an Idempotency-Key, the same on every retry)."""
        return await self._run(calls_submit_job(requests, label, kind, idempotency_key))

    async def job(self, job_id: str) -> JobPublic:
        """`Client.job`."""
        return await self._run(Call("GET", f"/v1/jobs/{job_id}", _json_as(JobPublic)))

    async def list_jobs(self, offset: int = 0, limit: int = 20) -> JobsPublic:
        """`Client.list_jobs`."""
        return await self._run(Call("GET", f"/v1/jobs?offset={int(offset)}&limit={int(limit)}",
                                    _json_as(JobsPublic)))

    async def cancel(self, job_id: str) -> JobPublic:
        """`Client.cancel`."""
        return await self._run(Call("DELETE", f"/v1/jobs/{job_id}", _json_as(JobPublic)))

    async def wait(self, job_id: str, timeout: float = 600.0, poll: float = 0.2) -> JobPublic:
        """`Client.wait`."""
        deadline = time.monotonic() + timeout
        while True:
            job = await self.job(job_id)
            if _finished(job, job_id, deadline, timeout):
                return job
            await asyncio.sleep(poll)

    async def results(self, job_id: str, kind: Optional[str] = None) -> JobOutcomes:
        """`Client.results`."""
        return await self._run(calls_results(job_id, kind or (await self.job(job_id)).kind))

    async def report(self, result: Union[FitResult, DiscoveryResult, dict],
                     request: Union[FitRequest, DiscoverRequest, dict, None] = None) -> str:
        """`Client.report`."""
        return await self._run(calls_report(result, request))

    async def job_report(self, job_id: str, index: int = 0) -> str:
        """`Client.job_report`."""
        return await self._run(Call("GET", f"/v1/jobs/{job_id}/report?index={int(index)}", _text))


def _finished(job: JobPublic, job_id: str, deadline: float, timeout: float) -> bool:
    if job.status in FINISHED:
        return True
    if time.monotonic() > deadline:
        raise TimeoutError(f"job {job_id} is still {job.status} after {timeout} s")
    return False


def _error_of(response: httpx.Response) -> GreyfitError:
    try:
        problem = response.json()
    except ValueError:
        problem = {"detail": response.text}
    return GreyfitError(response.status_code, problem if isinstance(problem, dict) else {"detail": problem},
                        _retry_after(response.headers.get("Retry-After")))


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
