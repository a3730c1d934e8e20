"""One measured experiment: time, inputs, outputs, optional known initial state and derivatives."""
from __future__ import annotations

from typing import Optional

from pydantic import BaseModel, ConfigDict, Field

from greyfit.schemas.limits import MAX_SAMPLES
from greyfit.schemas.model import Name
from greyfit.schemas.preprocess import Preprocess

# null marks a missing sample; NaN/inf are rejected with a named field later (JSON has no NaN).
Series = list[Optional[float]]


class Experiment(BaseModel):
    """Sampled data of one run; every series has one value per time sample."""

    model_config = ConfigDict(extra="forbid")

    name: Name = Field(default="experiment", description="names the record in results")
    time: list[float] = Field(min_length=2, max_length=MAX_SAMPLES, description="sample times, strictly increasing")
    inputs: dict[Name, Series] = Field(default_factory=dict, description="every input's series, complete")
    outputs: dict[Name, Series] = Field(
        default_factory=dict, description="measured outputs; null marks a missing sample (not fitted)")
    initial_state: dict[Name, float] = Field(
        default_factory=dict, description="known initial states; the others are estimated")
    derivatives: dict[Name, Series] = Field(
        default_factory=dict, description="measured dx/dt per state, used by equation error as given")
    preprocess: Optional[Preprocess] = Field(
        default=None, description="window, detrend, decimate: applied to every series before use")
