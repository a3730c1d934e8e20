"""Batch jobs: one job holds several requests, each a task with its own status and result."""
from __future__ import annotations

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
        requests=(list[request_schema], Field(min_length=1, fail_fast=True)),  # type: ignore[valid-type]
        label=(Optional[str], Field(default=None, max_length=200, pattern=LABEL_PATTERN)))
    return model




class TaskError(BaseModel):
    model_config = ON_FIRST_USE
    type: str
    field: Optional[str] = None
    detail: str
    errors: Optional[list[dict[str, Any]]] = None


class TaskPublic(BaseModel):
    model_config = ON_FIRST_USE
    index: int
    status: TaskStatus
    attempts: int
    started_at: Optional[float] = None
    finished_at: Optional[float] = None
    error: Optional[TaskError] = None


class JobProgress(BaseModel):
    model_config = ON_FIRST_USE
    done: int
    total: int
    succeeded: int
    failed: int


class JobSummary(BaseModel):
    """A job in the job list: its status and progress, without its tasks (GET /v1/jobs/{id} has them)."""
    model_config = ON_FIRST_USE
    id: str
    kind: str = Field(description="the task kind (service/task_kinds.py lists them; OpenAPI gives the enum)")
    label: Optional[str] = None
    status: JobStatus
    progress: JobProgress
    created_at: float
    started_at: Optional[float] = None
    finished_at: Optional[float] = None


class JobPublic(JobSummary):
    tasks: list[TaskPublic]


class JobsPublic(BaseModel):
    model_config = ON_FIRST_USE
    data: list[JobSummary]
    count: int


class TaskResult(BaseModel):
    model_config = ON_FIRST_USE
    index: int
    status: TaskStatus
    result: Optional[dict[str, Any]] = None
    error: Optional[TaskError] = None


class JobResults(BaseModel):
    model_config = ON_FIRST_USE
    id: str
    status: JobStatus
    results: list[TaskResult]
