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
    name: str = Field(description="the record's name")
    time: list[float] = Field(description="sample times [s]")
    states: dict[str, list[float]] = Field(description="per state, its simulated trajectory")
    outputs: dict[str, list[float]] = Field(description="per output, its simulated trajectory")
    initial_state: dict[str, float] = Field(description="the initial state used")
    initial_state_source: InitialStateSource = Field(
        description="experiment (its own initial_state), provided (the request's or the fit's), contiguous (where the "
                    "previous record ended) or estimated")
    estimated_states: list[str] = Field(
        description="states whose initial value was estimated from the record's first samples", default_factory=list)
    estimate_window: Optional[int] = Field(default=None, description="samples used to estimate them, else null")
    horizon: Optional[int] = Field(
        default=None, description="k of the k-step-ahead prediction in `predicted`")
    predicted: Optional[dict[str, list[float]]] = Field(
        default=None, description="ŷ(t | t-k): the model restarted k samples earlier from the measured "
                                  "states (unmeasured states from the simulation); the free simulation "
                                  "for the first k samples")
    note: Optional[str] = Field(default=None, description="a remark on this record, else null")


class SimulateRequest(BaseModel):
    """A model, parameter values, experiments (outputs optional) -> simulated states and outputs.

    Parameter values: the model's declared `value`s, overridden by `fit_result` (a FitResult or a
    DiscoveryResult, whose augmented model is used when `model` is omitted), overridden by
    `parameters`. A per-experiment estimate `k[exp]` applies to the experiment named `exp`.
    """

    model_config = ConfigDict(extra="forbid", defer_build=True)

    model: Optional[Model] = Field(
        default=None, description="the model (not needed with `fit_result`, which carries one)")
    parameters: dict[str, float] = Field(
        description="parameter values by name (override those of `fit_result`)", default_factory=dict)
    fit_result: Optional[Union[DiscoveryResult, FitResult]] = Field(
        default=None, description="a FitResult or DiscoveryResult: its model, estimates and initial states are used")
    experiments: list[Experiment] = Field(
        min_length=1, max_length=MAX_EXPERIMENTS,
        description="the records to simulate (inputs, and outputs where measured)")
    initial_states: dict[Name, dict[Name, float]] = Field(
        default_factory=dict, description="per experiment name; default: the experiment's initial_state, "
                                          "then fit_result's, else estimated on a leading window")
    options: FitOptions = Field(
        description="integration options (integrator, substeps, interpolation)", default_factory=FitOptions)
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

    parameters: dict[str, float] = Field(description="the parameter values used")
    experiments: list[SimulatedExperiment] = Field(description="per record, the simulated states and outputs")
    validation: Optional[ValidationResult] = Field(
        default=None, description="metrics against the measured outputs, where given")
    wall_time_s: float = Field(description="wall time in seconds")
