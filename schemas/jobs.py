"""Batch jobs: one job holds several requests, each a task with its own status and result."""
from __future__ import annotations

from datetime import datetime
from typing import Any, Literal, Optional

from pydantic import BaseModel, ConfigDict, Field, create_model

# The schemas a fit never uses are built on first use, not at import: importing the schemas (pydantic
# building ~75 models) was most of a fresh process's first-fit overhead, and a job's body repeats its
# request's whole schema.
ON_FIRST_USE = ConfigDict(defer_build=True)

JobStatus = Literal["queued", "running", "succeeded", "failed", "cancelled"]
TaskStatus = Literal["queued", "running", "succeeded", "failed", "cancelled"]


# no control characters (a NUL byte cannot be stored by PostgreSQL; the others break logs and pages),
# and no bidirectional controls (U+061C, U+200E-F, U+202A-E, U+2066-9: a right-to-left override makes
# a label read otherwise than it is stored, in every page and log that shows it)
LABEL_PATTERN = r"^[^\x00-\x1f\x7f\u061c\u200e\u200f\u202a-\u202e\u2066-\u2069]*$"


def job_create(name: str, request_schema: type[BaseModel], doc: str = "") -> type[BaseModel]:
    """The body of a batch job of `request_schema`s: {"requests": [...], "label": ...}.

    Assign it to a module-level name `name` in the request schema's own module: the body parser
    processes receive the class by that reference."""
    model = create_model(
        name, __config__=ConfigDict(extra="forbid", defer_build=True),
        __doc__=doc or f"A batch of {request_schema.__name__}s.",
        __module__=request_schema.__module__,
        # fail_fast: validation stops at the first invalid request (its errors are bounded; 250 000 empty
        # requests made 500 000 errors); the service says how many were not checked
        requests=(list[request_schema], Field(  # type: ignore[valid-type]
            min_length=1, fail_fast=True,
            description=f"the {request_schema.__name__}s to run, each a task of the job")),
        label=(Optional[str], Field(default=None, max_length=200, pattern=LABEL_PATTERN,
                                    description="a name for the job, shown in the job list")))
    return model




class TaskError(BaseModel):
    model_config = ON_FIRST_USE
    type: str = Field(description="the error's kind (e.g. ValidationError, ModelDefinitionError, Timeout, WorkerLost)")
    field: Optional[str] = Field(default=None, description="the request's field at fault, where there is one")
    detail: str = Field(description="what went wrong and the fix, in words")
    errors: Optional[list[dict[str, Any]]] = Field(default=None, description="validation errors, each {loc, msg}")


class TaskPublic(BaseModel):
    model_config = ON_FIRST_USE
    index: int = Field(description="the request's position in the job (0-based)")
    status: TaskStatus = Field(description="queued, running, succeeded, failed or cancelled")
    attempts: int = Field(description="how often a worker has started it (a lost worker's task is retried)")
    started_at: Optional[datetime] = Field(
        default=None, description="when its last attempt started (RFC 3339, UTC); null while queued")
    finished_at: Optional[datetime] = Field(
        default=None, description="when it finished (RFC 3339, UTC); null until then")
    error: Optional[TaskError] = Field(default=None, description="why it failed, else null")


class JobProgress(BaseModel):
    model_config = ON_FIRST_USE
    done: int = Field(description="tasks finished (succeeded, failed or cancelled)")
    total: int = Field(description="tasks in the job")
    succeeded: int = Field(description="tasks that succeeded")
    failed: int = Field(description="tasks that failed")


class JobSummary(BaseModel):
    """A job in the job list: its status and progress, without its tasks (GET /v1/jobs/{id} has them)."""
    model_config = ON_FIRST_USE
    id: str = Field(description="the job's id")
    kind: str = Field(description="the task kind (service/task_kinds.py lists them; OpenAPI gives the enum)")
    label: Optional[str] = Field(default=None, description="the label it was created with, else null")
    status: JobStatus = Field(
        description="queued, running, succeeded (at least one task did), failed (none did) or cancelled")
    progress: JobProgress = Field(description="counts of the job's tasks")
    created_at: datetime = Field(description="when the job was created (RFC 3339, UTC)")
    started_at: Optional[datetime] = Field(
        default=None, description="when its first task started (RFC 3339, UTC); null while queued")
    finished_at: Optional[datetime] = Field(
        default=None, description="when its last task finished (RFC 3339, UTC); null until then")


class JobPublic(JobSummary):
    tasks: list[TaskPublic] = Field(description="every task of the job, in request order")


class JobsPublic(BaseModel):
    model_config = ON_FIRST_USE
    data: list[JobSummary] = Field(description="the jobs of this page, newest first")
    count: int = Field(description="the number of all jobs")


class TaskResult(BaseModel):
    model_config = ON_FIRST_USE
    index: int = Field(description="the request's position in the job (0-based)")
    status: TaskStatus = Field(description="queued, running, succeeded, failed or cancelled")
    result: Optional[dict[str, Any]] = Field(
        default=None, description="the result (FitResult or DiscoveryResult, by the job's kind) once succeeded, else "
                                  "null")
    error: Optional[TaskError] = Field(default=None, description="why it failed, else null")


class JobResults(BaseModel):
    model_config = ON_FIRST_USE
    id: str = Field(description="the job's id")
    status: JobStatus = Field(description="the job's status")
    results: list[TaskResult] = Field(description="one entry per request, in request order")
