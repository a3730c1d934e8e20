"""A small typed client of the greyfit HTTP service.

    from greyfit.client import Client
    client = Client("http://127.0.0.1:8000", api_key=None)
    result = client.fit(request)            # a FitRequest (or its dict) -> FitResult

It uses only the standard library (urllib): calling greyfit must not add an HTTP stack to the
caller's environment, and JSON over HTTP/1.1 needs nothing more. Requests and results are the
service's own pydantic schemas.
"""
from __future__ import annotations

import json
import time
import urllib.error
import urllib.request
from typing import Any, Optional, Sequence, Union

from pydantic import BaseModel

from greyfit.schemas.discovery import DiscoverRequest, DiscoveryResult
from greyfit.schemas.fit import FitRequest, FitResult
from greyfit.schemas.frequency import FrequencyFitRequest
from greyfit.schemas.jobs import JobPublic, JobResults
from greyfit.schemas.simulate import SimulateRequest, SimulateResult

from greyfit.service.task_kinds import JOB_KINDS, KINDS

FINISHED = ("succeeded", "failed", "cancelled")


class GreyfitError(Exception):
    """An HTTP error answered by the service; `problem` is its problem+json body (when there is one)."""

    def __init__(self, status: int, problem: dict[str, Any]):
        self.status, self.problem = status, problem
        super().__init__(f"{status} {problem.get('title', '')}: {problem.get('detail', problem)}")


class Client:
    def __init__(self, base_url: str, api_key: Optional[str] = None, timeout: float = 600.0):
        self.base_url = base_url.rstrip("/")
        self.api_key = api_key
        self.timeout = timeout

    # --- plumbing --------------------------------------------------------------------------------
    def _request(self, method: str, path: str, body: Any = None) -> tuple[int, bytes]:
        data = None
        headers = {"accept": "application/json"}
        if body is not None:
            data = (body.model_dump_json() if isinstance(body, BaseModel) else json.dumps(body)).encode()
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
            raise GreyfitError(exc.code, problem if isinstance(problem, dict) else {"detail": problem}) from None

    def _json(self, method: str, path: str, body: Any = None) -> Any:
        return json.loads(self._request(method, path, body)[1])

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
                   label: Optional[str] = None, kind: str = "fit") -> JobPublic:
        """A batch job of fits (kind 'fit'), discoveries ('discover') or frequency-response fits
        ('frequency_fit'); returns at once."""
        if kind not in JOB_KINDS:
            raise ValueError(f"kind must be one of {list(JOB_KINDS)}")
        schema, path = KINDS[kind].request_schema(), KINDS[kind].jobs_path
        body = {"requests": [self._as(schema, r).model_dump(mode="json") for r in requests]}
        if label is not None:
            body["label"] = label
        return JobPublic.model_validate(self._json("POST", path, body))

    def job(self, job_id: str) -> JobPublic:
        return JobPublic.model_validate(self._json("GET", f"/v1/jobs/{job_id}"))

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

    def results(self, job_id: str) -> JobResults:
        """One entry per request (GET /v1/jobs/{id}/results); `result` is a dict, typed by the job's kind."""
        return JobResults.model_validate(self._json("GET", f"/v1/jobs/{job_id}/results"))

    def report(self, result: Union[FitResult, DiscoveryResult, dict],
               request: Union[FitRequest, DiscoverRequest, dict, None] = None) -> str:
        """The HTML report page of a result (POST /v1/report)."""
        body = {"result": result.model_dump(mode="json") if isinstance(result, BaseModel) else result}
        if request is not None:
            body["request"] = request.model_dump(mode="json") if isinstance(request, BaseModel) else request
        return self._request("POST", "/v1/report", body)[1].decode()

    def job_report(self, job_id: str, index: int = 0) -> str:
        return self._request("GET", f"/v1/jobs/{job_id}/report?index={index}")[1].decode()
