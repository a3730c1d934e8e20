"""The answers of the probes: GET /healthz (liveness) and GET /readyz (readiness)."""
from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, Field


class Health(BaseModel):
    """The process answers."""

    status: Literal["ok"] = Field(description="always ok: an answer at all is the news")


class Readiness(BaseModel):
    """The job store takes a write and the dispatcher runs (else 503 with a problem saying why)."""

    status: Literal["ready"] = Field(description="always ready (not ready is a 503)")
    executor: str = Field(description="where tasks run: local (worker processes of this server) or dask")
