"""Report request: a result (and the request that produced it, for the measured data)."""
from __future__ import annotations

from typing import Optional, Union

from pydantic import BaseModel, ConfigDict, Field

from greyfit.schemas.discovery import DiscoverRequest, DiscoveryResult
from greyfit.schemas.fit import FitRequest, FitResult


class ReportRequest(BaseModel):
    """Figures need the measured data: from `request` (simulated again at the result's estimates),
    or from the result's traces (`return_traces`). Without either, only the residual tests, the
    estimates and the correlations are drawn."""

    model_config = ConfigDict(extra="forbid")

    result: Union[DiscoveryResult, FitResult]
    request: Optional[Union[DiscoverRequest, FitRequest]] = None
    title: Optional[str] = Field(default=None, max_length=200)


class ReportPublic(BaseModel):
    html: str = Field(description="one self-contained page, figures embedded as base64 PNG")
    figures: list[str]
    notes: list[str] = Field(default_factory=list)
