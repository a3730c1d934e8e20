"""Simulation and validation: simulated trajectories, k-step-ahead predictions, validation metrics."""
from __future__ import annotations

from typing import Optional, Union

from pydantic import BaseModel, ConfigDict, Field

from greyfit.schemas.discovery import DiscoveryResult
from greyfit.schemas.experiment import Experiment
from greyfit.schemas.fit import FitOptions, FitResult
from greyfit.schemas.jobs import ON_FIRST_USE
from greyfit.schemas.limits import MAX_EXPERIMENTS
from greyfit.schemas.model import Model, Name
from greyfit.schemas.validation import InitialStateSource, ValidationResult


class SimulatedExperiment(BaseModel):
    model_config = ON_FIRST_USE
    name: str
    time: list[float]
    states: dict[str, list[float]]
    outputs: dict[str, list[float]]
    initial_state: dict[str, float]
    initial_state_source: InitialStateSource
    estimated_states: list[str] = Field(default_factory=list)
    estimate_window: Optional[int] = None
    horizon: Optional[int] = Field(
        default=None, description="k of the k-step-ahead prediction in `predicted`")
    predicted: Optional[dict[str, list[float]]] = Field(
        default=None, description="ŷ(t | t-k): the model restarted k samples earlier from the measured "
                                  "states (unmeasured states from the simulation); the free simulation "
                                  "for the first k samples")
    note: Optional[str] = None


class SimulateRequest(BaseModel):
    """A model, parameter values, experiments (outputs optional) -> simulated states and outputs.

    Parameter values: the model's declared `value`s, overridden by `fit_result` (a FitResult or a
    DiscoveryResult, whose augmented model is used when `model` is omitted), overridden by
    `parameters`. A per-experiment estimate `k[exp]` applies to the experiment named `exp`.
    """

    model_config = ConfigDict(extra="forbid", defer_build=True)

    model: Optional[Model] = None
    parameters: dict[str, float] = Field(default_factory=dict)
    fit_result: Optional[Union[DiscoveryResult, FitResult]] = None
    experiments: list[Experiment] = Field(min_length=1, max_length=MAX_EXPERIMENTS)
    initial_states: dict[Name, dict[Name, float]] = Field(
        default_factory=dict, description="per experiment name; default: the experiment's initial_state, "
                                          "then fit_result's, else estimated on a leading window")
    options: FitOptions = Field(default_factory=FitOptions)
    horizon: Optional[int] = Field(default=None, ge=1, description="also return k-step-ahead predictions")
    estimate_window: Optional[int] = Field(
        default=None, ge=2, description="samples of the leading window for initial-state estimation")


class SimulateResult(BaseModel):
    """Simulated states and outputs per record, the parameters used, and metrics where outputs were given."""
    model_config = ON_FIRST_USE

    def report(self) -> str:
        """A text report for people (`greyfit ... --summary` prints it)."""
        from greyfit.schemas.text_report import simulate_report
        return simulate_report(self)

    def __str__(self) -> str:
        return self.report()

    parameters: dict[str, float]
    experiments: list[SimulatedExperiment]
    validation: Optional[ValidationResult] = Field(
        default=None, description="metrics against the measured outputs, where given")
    wall_time_s: float
