"""Batch jobs: one job holds several requests, each a task with its own status and result."""
from __future__ import annotations

from typing import Any, Literal, Optional

from pydantic import BaseModel, ConfigDict, Field

from greyfit.schemas.fit import FitRequest
from greyfit.schemas.frequency import FrequencyFitRequest

JobStatus = Literal["queued", "running", "succeeded", "failed", "cancelled"]
TaskStatus = Literal["queued", "running", "succeeded", "failed", "cancelled"]


class JobCreate(BaseModel):
    model_config = ConfigDict(extra="forbid")

    requests: list[FitRequest] = Field(min_length=1)
    label: Optional[str] = Field(default=None, max_length=200)


class FrequencyJobCreate(BaseModel):
    """A batch of frequency-response fits (POST /v1/frequency-fits/jobs)."""

    model_config = ConfigDict(extra="forbid")

    requests: list[FrequencyFitRequest] = Field(min_length=1)
    label: Optional[str] = Field(default=None, max_length=200)


class TaskError(BaseModel):
    type: str
    field: Optional[str] = None
    detail: str
    errors: Optional[list[dict[str, Any]]] = None


class TaskPublic(BaseModel):
    index: int
    status: TaskStatus
    attempts: int
    started_at: Optional[float] = None
    finished_at: Optional[float] = None
    error: Optional[TaskError] = None


class JobProgress(BaseModel):
    done: int
    total: int
    succeeded: int
    failed: int


class JobPublic(BaseModel):
    id: str
    kind: Literal["fit", "discover", "frequency_fit"]
    label: Optional[str] = None
    status: JobStatus
    progress: JobProgress
    created_at: float
    started_at: Optional[float] = None
    finished_at: Optional[float] = None
    tasks: list[TaskPublic]


class JobsPublic(BaseModel):
    data: list[JobPublic]
    count: int


class TaskResult(BaseModel):
    index: int
    status: TaskStatus
    result: Optional[dict[str, Any]] = None
    error: Optional[TaskError] = None


class JobResults(BaseModel):
    id: str
    status: JobStatus
    results: list[TaskResult]
