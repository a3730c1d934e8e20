"""One measured experiment: time, inputs, outputs, optional known initial state and derivatives."""
from __future__ import annotations

from typing import Optional

from pydantic import BaseModel, ConfigDict, Field

from greyfit.schemas.limits import MAX_SAMPLES
from greyfit.schemas.model import FiniteFloat, Name
from greyfit.schemas.preprocess import Preprocess

# null marks a missing sample. NaN and ±inf are refused here, where every path validates (the library,
# the command line, each route, the client), with one message naming the sample: a request that reached a
# solver with them would fit one sample fewer on a path that had written NaN as null (JSON has no NaN).
Series = list[Optional[FiniteFloat]]


class Experiment(BaseModel):
    """Sampled data of one run; every series has one value per time sample."""

    # a NaN put into a validated record (a list changed in place) is written as NaN, never as null: the
    # receiver refuses it as it would here, instead of fitting one sample fewer
    model_config = ConfigDict(extra="forbid", ser_json_inf_nan="constants")

    name: Name = Field(default="experiment", description="names the record in results")
    time: list[FiniteFloat] = Field(min_length=2, max_length=MAX_SAMPLES,
                                    description="sample times, strictly increasing")
    inputs: dict[Name, Series] = Field(default_factory=dict, description="every input's series, complete")
    outputs: dict[Name, Series] = Field(
        default_factory=dict, description="measured outputs; null marks a missing sample (not fitted)")
    initial_state: dict[Name, FiniteFloat] = Field(
        default_factory=dict, description="known initial states; the others are estimated")
    derivatives: dict[Name, Series] = Field(
        default_factory=dict, description="measured dx/dt per state, used by equation error as given")
    preprocess: Optional[Preprocess] = Field(
        default=None, description="window, detrend, decimate: applied to every series before use")
