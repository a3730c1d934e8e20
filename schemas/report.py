"""Report request: a result (and the request that produced it, for the measured data)."""
from __future__ import annotations

from typing import Annotated, Optional, Union

from pydantic import BaseModel, ConfigDict, Discriminator, Field, Tag

from greyfit.schemas.discovery import DiscoverRequest, DiscoveryResult
from greyfit.schemas.fit import FitRequest, FitResult
from greyfit.schemas.frequency import FrequencyFitRequest

FREQUENCY_MODEL_KINDS = ("transfer_function", "linearised_ode")


def _result_kind(value) -> str:
    """A discovery result has a `conclusion`; anything else is read as a fit result."""
    if isinstance(value, dict):
        return "discovery" if "conclusion" in value else "fit"
    return "discovery" if isinstance(value, DiscoveryResult) else "fit"


def _request_kind(value) -> str:
    """One schema per request, chosen by what it says (so errors name that schema's fields, not a
    union's internals): model kind transfer_function/linearised_ode or `data` → a frequency fit,
    `discovery` → a discover request, else a fit request."""
    if not isinstance(value, dict):
        if isinstance(value, FrequencyFitRequest):
            return "frequency_fit"
        return "discover" if isinstance(value, DiscoverRequest) else "fit"
    model = value.get("model")
    if (isinstance(model, dict) and model.get("kind") in FREQUENCY_MODEL_KINDS) or "data" in value:
        return "frequency_fit"
    return "discover" if "discovery" in value else "fit"


AnyResult = Annotated[Union[Annotated[DiscoveryResult, Tag("discovery")], Annotated[FitResult, Tag("fit")]],
                      Discriminator(_result_kind)]
AnyRequest = Annotated[Union[Annotated[DiscoverRequest, Tag("discover")], Annotated[FitRequest, Tag("fit")],
                             Annotated[FrequencyFitRequest, Tag("frequency_fit")]],
                       Discriminator(_request_kind)]


class ReportRequest(BaseModel):
    """Figures need the measured data: from `request` (simulated again with the model the result
    carries, at its estimates), or from the result's traces (`return_traces`). Without either, only
    the residual tests, the estimates and the correlations are drawn. A frequency fit's result
    holds its measured and fitted responses: its Bode and Nyquist figures need no request."""

    model_config = ConfigDict(extra="forbid")

    result: AnyResult = Field(description="a FitResult (time-domain or frequency) or DiscoveryResult")
    request: Optional[AnyRequest] = Field(
        default=None, description="the request of that result: its records are simulated again for the compare figures")
    title: Optional[str] = Field(description="the page's title", default=None, max_length=200)


class ReportPublic(BaseModel):
    html: str = Field(description="one self-contained page, figures embedded as base64 PNG")
    figures: list[str]
    notes: list[str] = Field(default_factory=list)
