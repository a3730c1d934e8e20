"""Experiment design: the input signal that shrinks the intervals or separates rival models."""
from __future__ import annotations

import math
from typing import Annotated, Literal, Optional

from pydantic import BaseModel, ConfigDict, Field, model_validator

from greyfit.schemas.experiment import Experiment
from greyfit.schemas.fit import FitResult
from greyfit.schemas.jobs import ON_FIRST_USE, job_create
from greyfit.schemas.model import FiniteFloat, Model, Name

MAX_DESIGN_SAMPLES = 20_000
MAX_DESIGN_PIECES = 2_000
MAX_RIVALS = 4
MAX_DRAWS = 10

Criterion = Literal["D", "A", "E", "T"]


class InputLimits(BaseModel):
    """What one input may do: designed between `lower` and `upper`, or held at `value`."""

    model_config = ConfigDict(extra="forbid")

    lower: Optional[FiniteFloat] = Field(default=None, description="the smallest value the input may take")
    upper: Optional[FiniteFloat] = Field(default=None, description="the largest value the input may take")
    max_rate: Optional[float] = Field(
        default=None, gt=0, allow_inf_nan=False,
        description="the largest change per second between two held values (|Δu|/hold); omit for none")
    value: Optional[FiniteFloat] = Field(
        default=None, description="hold this input at `value` instead of designing it (then omit lower/upper)")

    @model_validator(mode="after")
    def _free_or_fixed(self) -> "InputLimits":
        if self.value is not None:
            if self.lower is not None or self.upper is not None:
                raise ValueError("give either `value` (the input is held) or `lower` and `upper` (it is "
                                 "designed), not both")
            return self
        if self.lower is None or self.upper is None:
            raise ValueError("a designed input needs both `lower` and `upper` (or `value` to hold it)")
        if not self.lower < self.upper:
            raise ValueError(f"lower ({self.lower}) must be below upper ({self.upper})")
        return self

    @property
    def free(self) -> bool:
        """Whether the design chooses this input."""
        return self.value is None


class RivalModel(BaseModel):
    """A rival explanation of the same data: its parameters are refitted to the model's prediction."""

    model_config = ConfigDict(extra="forbid")

    name: Name = Field(default="rival", description="names the rival in the result")
    model: Model = Field(description="the rival model; its outputs must include every measured output")


class DesignOptions(BaseModel):
    """How hard the design's optimiser works; the defaults suit records of up to a few thousand samples."""

    model_config = ConfigDict(extra="forbid")

    starts: int = Field(default=3, ge=1, le=10, description="starting signals (seeded random levels, and the "
                        "baseline's input where it lies on the hold grid); the best design is kept")
    max_iterations: int = Field(default=150, ge=1, le=2000, description="Ipopt iterations per start")
    substeps: int = Field(default=2, ge=1, le=50, description="RK4 steps per sample in the design's simulation")
    seed: int = Field(default=0, ge=0, le=2**31 - 1,
                      description="seeds the starting signals and the parameter draws (a non-negative integer)")
    rounds: int = Field(default=3, ge=1, le=10,
                        description="T-optimal only: rounds of (refit the rivals, redesign the input)")


class DesignRequest(BaseModel):
    """A model, its parameters' estimates, the input's limits and the measured outputs -> an input signal.

    The parameters: the model's declared `value`s, overridden by `fit_result`'s estimates (its model
    is used when `model` is omitted), overridden by `parameters`. The criterion is D-optimal by
    default (the determinant of the parameters' covariance, smallest), A (the sum of their relative
    variances) or E (the largest relative variance); T-optimal maximises the smallest divergence between
    the model's outputs and each rival's best imitation of them. The initial state is taken as known.
    """

    model_config = ConfigDict(extra="forbid", defer_build=True)

    model: Optional[Model] = Field(default=None, description="the model to design for; default: fit_result's")
    fit_result: Optional[FitResult] = Field(
        default=None, description="a result of a fit of the model: its estimates, covariance (for "
                                  "`robust_draws`) and model")
    parameters: dict[Name, FiniteFloat] = Field(
        default_factory=dict, description="parameter values overriding the model's and fit_result's")
    parameters_of_interest: list[Name] = Field(
        default_factory=list, description="the parameters whose intervals the design shrinks (D, A, E); "
                                          "default: every free parameter")
    inputs: dict[Name, InputLimits] = Field(
        description="every model input: its limits (designed) or a held `value`; at least one designed")
    outputs: dict[Name, float] = Field(
        min_length=1, description="the outputs that will be measured, each with its noise standard deviation")
    duration: float = Field(gt=0, allow_inf_nan=False, description="length of the experiment in seconds")
    sample_time: float = Field(gt=0, allow_inf_nan=False, description="seconds between measured samples")
    hold: Optional[float] = Field(
        default=None, gt=0, allow_inf_nan=False,
        description="seconds each designed value is held (a whole number of samples); default: sample_time")
    initial_state: dict[Name, FiniteFloat] = Field(
        default_factory=dict, description="every state's value at t = 0 (default 0)")
    criterion: Criterion = Field(default="D", description="D, A, E (information) or T (discriminate rivals)")
    rivals: list[RivalModel] = Field(default_factory=list, max_length=MAX_RIVALS,
                                     description="T-optimal: the rival models to tell the model from")
    signal: Literal["piecewise_constant", "multisine"] = Field(
        default="piecewise_constant",
        description="piecewise constant on the hold grid, or a sum of sines at `frequencies` (levels held "
                    "for one sample)")
    frequencies: Optional[list[Annotated[float, Field(gt=0, allow_inf_nan=False)]]] = Field(
        default=None, max_length=64, description="multisine: the frequencies in Hz (default: eight, "
                                                 "log-spaced from 1/duration to a fifth of the sampling rate)")
    robust_draws: int = Field(
        default=0, ge=0, le=MAX_DRAWS, description="average the criterion over this many parameter draws from "
                                                   "fit_result's covariance (0: at the estimates only)")
    baseline: Optional[Experiment] = Field(
        default=None, description="the experiment that was run: its input's predicted standard errors (or "
                                  "discrimination) are reported beside the design's")
    options: DesignOptions = Field(default_factory=DesignOptions,
                                   description="the optimiser's starts, iterations, seed and simulation steps")

    @model_validator(mode="after")
    def _consistent(self) -> "DesignRequest":
        if self.model is None and (self.fit_result is None or self.fit_result.model is None):
            raise ValueError("give `model`, or a `fit_result` that carries its model")
        if self.criterion == "T" and not self.rivals:
            raise ValueError("criterion T needs at least one model in `rivals`")
        for name, std in self.outputs.items():
            if not (math.isfinite(std) and std > 0):
                raise ValueError(f"outputs.{name}: the noise standard deviation must be positive and finite")
        samples = self.duration / self.sample_time
        if samples < 2:
            raise ValueError("duration must span at least two sample times")
        if samples > MAX_DESIGN_SAMPLES:
            raise ValueError(f"duration / sample_time = {samples:.0f} samples; at most {MAX_DESIGN_SAMPLES}")
        if self.hold is not None:
            ratio = self.hold / self.sample_time
            if abs(ratio - round(ratio)) > 1e-6 or round(ratio) < 1:
                raise ValueError(f"hold ({self.hold}) must be a whole number of sample times ({self.sample_time})")
        return self


class PredictedParameter(BaseModel):
    """A parameter of interest's predicted standard error with the designed input and with the baseline's."""

    model_config = ON_FIRST_USE
    value: float = Field(description="the value the prediction is made at")
    stderr: Optional[float] = Field(description="predicted standard error with the designed input")
    stderr_baseline: Optional[float] = Field(
        default=None, description="predicted standard error with the baseline's input, where given")


class Discrimination(BaseModel):
    """How far a rival's best imitation of the truth stays from it, on the designed and the baseline input."""

    model_config = ON_FIRST_USE
    rival: str = Field(description="the rival's name: the model refitted to imitate the truth")
    truth: str = Field(description="which model generates the data in this comparison")
    divergence: float = Field(description="Σ((y_truth − y_rival)/σ)² with the rival refitted to the truth's "
                                          "outputs on the designed input: the expected rise of the rival's χ²")
    divergence_baseline: Optional[float] = Field(default=None, description="the same on the baseline's input")
    expected_delta_bic: float = Field(description="divergence + (rival's free parameters − truth's)·ln N: "
                                                  "the expected BIC in favour of the truth")
    expected_delta_bic_baseline: Optional[float] = Field(
        default=None, description="the same on the baseline's input, where given")
    rival_parameters: dict[str, float] = Field(description="the rival's parameters imitating the truth best")
    settle_probability: Optional[float] = Field(
        default=None, description="the chance that a record made with the designed input gives a ΔBIC above the "
                                  "discovery loop's ambiguity margin (10) for this pair: Φ((expected ΔBIC − 10)/"
                                  "(2√divergence)), the noise's cross term being normal with variance 4·divergence")
    duration_to_settle: Optional[float] = Field(
        default=None, description="where settle_probability is below 0.9: the duration (s) at which it would reach "
                                  "0.9 with the same amplitude, taking the divergence as growing in proportion to the "
                                  "record's length (design again with it); null when the design settles it")


class DesignResult(BaseModel):
    """The designed experiment (its input; outputs to be measured) and what it is predicted to give."""

    model_config = ON_FIRST_USE

    def report(self) -> str:
        """A text report for people (`greyfit design --summary` prints it)."""
        from greyfit.schemas.text_report import design_report
        return design_report(self)

    def __str__(self) -> str:
        return self.report()

    criterion: Criterion = Field(description="the criterion the input was designed for")
    experiment: Experiment = Field(description="the input to apply (time, inputs); outputs are to be measured")
    objective: float = Field(description="the criterion's value for the design (smaller is better for D, A, E: "
                                         "log det, trace, largest of the relative covariance; T: −divergence)")
    objective_baseline: Optional[float] = Field(
        default=None, description="the criterion's value for the baseline's input, where given")
    parameters: dict[str, PredictedParameter] = Field(
        default_factory=dict, description="per parameter of interest: predicted standard errors")
    discrimination: list[Discrimination] = Field(
        default_factory=list, description="T: per ordered pair (truth, rival), the divergence on the design and "
                                          "on the baseline")
    improvement: Optional[float] = Field(
        default=None, description="D, A, E: the baseline's largest predicted stderr of a parameter of interest "
                                  "divided by the design's for that parameter; T: the smallest divergence "
                                  "over the baseline's")
    status: str = Field(description="Ipopt's status for the kept start")
    iterations: int = Field(description="Ipopt iterations of the kept start (T: over its rounds)")
    notes: list[str] = Field(default_factory=list, description="what the prediction assumes")
    wall_time_s: float = Field(description="wall time of the design in seconds")


DesignJobCreate = job_create("DesignJobCreate", DesignRequest, "A batch of experiment designs.")
