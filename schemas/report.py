"""Report request: a result (and the request that produced it, for the measured data)."""
from __future__ import annotations

from typing import Annotated, Optional, Union

from pydantic import BaseModel, ConfigDict, Discriminator, Field, Tag, model_validator

from greyfit.schemas.design import DesignRequest, DesignResult
from greyfit.schemas.discovery import DiscoverRequest, DiscoveryResult
from greyfit.schemas.fit import FitRequest, FitResult
from greyfit.schemas.frequency import FrequencyFitRequest

FREQUENCY_MODEL_KINDS = ("transfer_function", "linearised_ode")


def _result_kind(value) -> str:
    """A discovery result has a `conclusion`, a design result a `criterion` and an `experiment`;
    anything else is read as a fit result."""
    if isinstance(value, dict):
        if "conclusion" in value:
            return "discovery"
        return "design" if "criterion" in value and "experiment" in value else "fit"
    if isinstance(value, DesignResult):
        return "design"
    return "discovery" if isinstance(value, DiscoveryResult) else "fit"


def _request_kind(value) -> str:
    """One schema per request, chosen by what it says (so errors name that schema's fields, not a
    union's internals): model kind transfer_function/linearised_ode or `data` → a frequency fit,
    `discovery` → a discover request, `duration` and `sample_time` → a design request, else a fit
    request."""
    if not isinstance(value, dict):
        if isinstance(value, FrequencyFitRequest):
            return "frequency_fit"
        if isinstance(value, DesignRequest):
            return "design"
        return "discover" if isinstance(value, DiscoverRequest) else "fit"
    if "duration" in value and "sample_time" in value:
        return "design"
    model = value.get("model")
    if (isinstance(model, dict) and model.get("kind") in FREQUENCY_MODEL_KINDS) or "data" in value:
        return "frequency_fit"
    return "discover" if "discovery" in value else "fit"


AnyResult = Annotated[Union[Annotated[DiscoveryResult, Tag("discovery")], Annotated[FitResult, Tag("fit")],
                            Annotated[DesignResult, Tag("design")]],
                      Discriminator(_result_kind)]
AnyRequest = Annotated[Union[Annotated[DiscoverRequest, Tag("discover")], Annotated[FitRequest, Tag("fit")],
                             Annotated[FrequencyFitRequest, Tag("frequency_fit")],
                             Annotated[DesignRequest, Tag("design")]],
                       Discriminator(_request_kind)]


class ReportRequest(BaseModel):
    """Figures need the measured data: from `request` (simulated again with the model the result
    carries, at its estimates), or from the result's traces (`return_traces`). Without either, only
    the residual tests, the estimates and the correlations are drawn. A frequency fit's result
    holds its measured and fitted responses: its Bode and Nyquist figures need no request."""

    model_config = ConfigDict(extra="forbid")

    result: AnyResult = Field(description="a FitResult (time-domain or frequency), DiscoveryResult or DesignResult")
    request: Optional[AnyRequest] = Field(
        default=None, description="the request of that result: its records are simulated again for the compare figures")
    title: Optional[str] = Field(description="the page's title", default=None, max_length=200)

    @model_validator(mode="after")
    def _request_of_the_result(self) -> "ReportRequest":
        design_result = isinstance(self.result, DesignResult)
        if self.request is not None and design_result != isinstance(self.request, DesignRequest):
            raise ValueError("request: give the request that produced the result (a DesignRequest goes with a "
                             "DesignResult, a fit's or discovery's request with its result)")
        return self


class ReportPublic(BaseModel):
    html: str = Field(description="one self-contained page, figures embedded as base64 PNG")
    figures: list[str]
    notes: list[str] = Field(default_factory=list)
