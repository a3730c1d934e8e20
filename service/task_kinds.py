"""The one table of task kinds: what a worker runs, what routes, jobs, the CLI batch and the client offer.

Why: a kind used to be spelt in five places (the worker's runners, the jobs schema's Literal, the
CLI batch's schema table, the client's job table, the routes), so a new route with jobs cost eight
files. Every one of those now reads `KINDS`, and so do the OpenAPI description (which paths answer
synchronously, the example bodies) and the tests that send every route its example. A new kind is
its schemas, its solver function and one entry here; `service/http/routes/tasks.py` makes its synchronous
and job routes from the entry.

This module imports only the schemas and the standard library: the client reads it too.
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Callable, Optional

from pydantic import BaseModel

if TYPE_CHECKING:
    from greyfit.schemas.report import ReportPublic, ReportRequest


def _load(path: str) -> Any:
    module, _, name = path.partition(":")
    return getattr(importlib.import_module(module), name)


@dataclass(frozen=True)
class Example:
    """An example request body for the OpenAPI description: a real request that works as sent.

    `body` is the "module:name" path of a function () -> dict, called when the description is built.
    """

    name: str      # its key in the description's components/examples
    summary: str
    body: str

    def build(self) -> dict:
        return _load(self.body)()


@dataclass(frozen=True)
class TaskKind:
    """One kind of task.

    `request`, `result` and `run` are "module:name" paths, loaded on first use, so that reading
    the table (the client, the CLI's argument parser) imports neither CasADi nor matplotlib.
    """

    name: str
    request: str                      # the request schema
    result: str                       # the result schema
    run: str                          # function(request) -> result, in solvers/ (or service/ for pages)
    caps_cpu: bool = True             # options.max_cpu_time is capped below the worker's CPU limit
    sync_path: Optional[str] = None   # POST route answering synchronously (generated when `generate`)
    example: Optional[Example] = None   # the sync route's example body (OpenAPI; the tests send it)
    jobs_path: Optional[str] = None   # POST route taking a batch job of these (generated when `generate`)
    job_body: Optional[str] = None    # the job body schema (`schemas.jobs.job_create`), with jobs_path
    job_example: Optional[Example] = None   # the jobs route's example body (else none is shown)
    limits: str = "greyfit.service.http.limits:check_limits"    # check(request, settings, prefix)
    values: str = "greyfit.service.http.limits:data_values"     # number of data values (sync size limit)
    tag: str = "fits"
    summary: str = ""                 # the sync route's docstring (OpenAPI)
    job_summary: str = ""
    elsewhere: str = ""               # where a request too large for a synchronous answer belongs
    operation: str = ""               # the sync route's function name (OpenAPI operationId)
    job_operation: str = ""
    generate: bool = True             # False: its routes are written by hand (simulate, report)

    def request_schema(self) -> type[BaseModel]:
        return _load(self.request)

    def result_schema(self) -> type[BaseModel]:
        return _load(self.result)

    def runner(self) -> Callable[[BaseModel], BaseModel]:
        return _load(self.run)

    def job_schema(self) -> type[BaseModel]:
        if self.job_body is None:
            raise LookupError(f"task kind {self.name} takes no jobs")
        return _load(self.job_body)

    def check(self) -> Callable[..., None]:
        return _load(self.limits)

    def count(self) -> Callable[[Any], int]:
        return _load(self.values)


_FREQ_LIMITS = "greyfit.service.http.limits:check_frequency_limits"
_EXAMPLES = "greyfit.service.http.openapi_examples"

KINDS: dict[str, TaskKind] = {k.name: k for k in (
    TaskKind("fit", "greyfit.schemas.fit:FitRequest", "greyfit.schemas.fit:FitResult",
             "greyfit.solvers.fit:fit_model", sync_path="/v1/fits", jobs_path="/v1/jobs",
             job_body="greyfit.schemas.fit:JobCreate",
             example=Example("msd_fit", "Mass-spring-damper m x'' + c x' + k x = u: c and k from noisy x and v",
                             f"{_EXAMPLES}:msd_fit"),
             job_example=Example("msd_job", "The mass-spring-damper fit as a batch job of one request",
                                 f"{_EXAMPLES}:msd_job"),
             summary="Run one fit synchronously (small problems); larger ones belong in /v1/jobs.",
             job_summary="Accept a batch of fits; each request becomes a task. Poll the Location header.",
             elsewhere='Submit it as a batch job: POST /v1/jobs {"requests": [<this body>]}',
             operation="create_fit", job_operation="create_fit_job", tag="fits"),
    TaskKind("discover", "greyfit.schemas.discovery:DiscoverRequest", "greyfit.schemas.discovery:DiscoveryResult",
             "greyfit.solvers.discovery:discover", sync_path="/v1/discover", jobs_path="/v1/discover/jobs",
             job_body="greyfit.schemas.discovery:DiscoverJobCreate",
             example=Example("msd_discover", "The mass-spring-damper fit, then a search for an effect it lacks "
                             "(its model is complete: nothing is added)", f"{_EXAMPLES}:msd_discover"),
             summary="Fit, trace the residual to a missing physical effect, add it, refit: before/after and "
                     "evidence.",
             job_summary="Discovery requests as a batch job; results at /v1/jobs/{id}/results.",
             elsewhere="Submit it as a job: POST /v1/discover/jobs",
             operation="create_discovery", job_operation="create_discovery_job", tag="discovery"),
    TaskKind("frequency_fit", "greyfit.schemas.frequency:FrequencyFitRequest", "greyfit.schemas.fit:FitResult",
             "greyfit.solvers.frequency:fit_frequency_response", sync_path="/v1/frequency-fits",
             jobs_path="/v1/frequency-fits/jobs", job_body="greyfit.schemas.frequency:FrequencyJobCreate",
             limits=_FREQ_LIMITS,
             values="greyfit.service.http.limits:frequency_values",
             example=Example("pi_loop", "A fourth-order plant measured in a PI loop at two controller "
                             "settings (Parameter estimation from frequency data, Ohki)",
                             f"{_EXAMPLES}:frequency_pi_loop"),
             summary="Fit a transfer-function model (optionally in a known feedback loop) to frequency "
                     "responses.",
             job_summary="Frequency-response fits as a batch job; results at /v1/jobs/{id}/results.",
             elsewhere="Decimate the sine-test records, or submit it as a job: POST /v1/frequency-fits/jobs",
             operation="create_frequency_fit", job_operation="create_frequency_fit_job", tag="frequency fits"),
    TaskKind("design", "greyfit.schemas.design:DesignRequest", "greyfit.schemas.design:DesignResult",
             "greyfit.solvers.design:design_experiment", caps_cpu=False,   # bounded by its iterations and starts
             sync_path="/v1/designs", jobs_path="/v1/designs/jobs",
             job_body="greyfit.schemas.design:DesignJobCreate",
             limits="greyfit.service.http.limits:check_design_limits",
             values="greyfit.service.http.limits:design_values",
             example=Example("msd_design", "The input that shrinks the mass-spring-damper's intervals most "
                             "(D-optimal), beside the single step that was run", f"{_EXAMPLES}:msd_design"),
             summary="Design the next experiment's input: D/A/E-optimal for the parameters' intervals, or "
                     "T-optimal to tell rival models apart.",
             job_summary="Experiment designs as a batch job; results at /v1/jobs/{id}/results.",
             elsewhere="Submit it as a job: POST /v1/designs/jobs",
             operation="create_design", job_operation="create_design_job", tag="designs"),
    TaskKind("simulate", "greyfit.schemas.simulate:SimulateRequest", "greyfit.schemas.simulate:SimulateResult",
             "greyfit.solvers.simulation.simulate:simulate_request", caps_cpu=False, generate=False,
             sync_path="/v1/simulate",   # service/http/routes/simulate.py
             example=Example("msd_simulate", "The mass-spring-damper record simulated with c = 0.8, k = 5",
                             f"{_EXAMPLES}:msd_simulation")),
    TaskKind("report", "greyfit.schemas.report:ReportRequest", "greyfit.schemas.report:ReportPublic",
             "greyfit.service.task_kinds:run_report", caps_cpu=False, generate=False,
             sync_path="/v1/report"),   # service/http/routes/report.py
)}

TASK_KINDS = tuple(KINDS)
JOB_KINDS = tuple(name for name, k in KINDS.items() if k.jobs_path)


def run_report(request: ReportRequest) -> ReportPublic:
    """The report page of a result (matplotlib: in a worker, never in the web process)."""
    from greyfit.service.report.page import report_public
    from greyfit.solvers.errors import DataError
    try:
        return report_public(request)
    except (ValueError, OverflowError, TypeError, KeyError, IndexError, ArithmeticError) as exc:
        # a result that was not made by greyfit (odd keys, values near the float limits) cannot
        # be drawn: that is the caller's input, not a server fault
        raise DataError(f"this result cannot be drawn ({type(exc).__name__}: {exc}); send a result "
                        "as greyfit returned it", "result") from exc
