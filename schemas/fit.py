"""Fit request and the one documented fit result type (lmfit/scipy style)."""
from __future__ import annotations

from enum import Enum
from typing import Literal, Optional

import math

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from schemas.experiment import Experiment
from schemas.limits import MAX_EXPERIMENTS
from schemas.model import Model, Name


class FitMethod(str, Enum):
    equation_error = "equation_error"
    single_shooting = "single_shooting"
    multiple_shooting = "multiple_shooting"


class FitOptions(BaseModel):
    """Solver options; every field has a sensible default."""

    model_config = ConfigDict(extra="forbid")

    integrator: Literal["rk4", "cvodes"] = "rk4"
    substeps: int = Field(default=1, ge=1, le=100, description="RK4 steps per sample interval")
    input_interpolation: Literal["foh", "zoh"] = Field(
        default="foh", description="inputs between samples: linear (foh) or held (zoh)")
    shooting_interval: int = Field(
        default=1, ge=1, le=10_000, description="samples per multiple-shooting interval")
    hessian: Literal["gauss_newton", "exact"] = "gauss_newton"
    max_iter: int = Field(default=200, ge=1, le=10_000)
    max_cpu_time: float = Field(default=120.0, gt=0, le=86_400)
    tol: float = Field(default=1e-8, gt=0, lt=1)
    multistart: int = Field(default=1, ge=1, le=100, description="starts drawn inside the bounds; best kept")
    seed: int = Field(default=0, description="random seed for multistart")
    output_weights: dict[Name, float] = Field(
        default_factory=dict,
        description="weight per output; default 1/std of the measured output")
    derivative_window: int = Field(
        default=11, ge=5, le=1001,
        description="Savitzky-Golay window (odd, samples) for derivatives estimated by equation error")
    derivative_order: int = Field(default=3, ge=2, le=6, description="Savitzky-Golay polynomial order")
    return_traces: bool = Field(default=False, description="include simulated outputs and residuals")
    confidence_level: float = Field(default=0.95, gt=0.5, lt=1)

    @field_validator("output_weights")
    @classmethod
    def _weights_positive(cls, weights: dict[str, float]) -> dict[str, float]:
        for name, w in weights.items():
            if not (math.isfinite(w) and w > 0):
                raise ValueError(f"output_weights.{name} = {w}: a weight must be a finite number > 0 "
                                 "(leave the output out of output_weights for the default 1/std)")
        return weights

    @field_validator("derivative_window")
    @classmethod
    def _window_odd(cls, window: int) -> int:
        if window % 2 == 0:
            raise ValueError(f"{window} is even; a Savitzky-Golay window is centred: use {window + 1}")
        return window

    @model_validator(mode="after")
    def _order_below_window(self) -> "FitOptions":
        if self.derivative_order >= self.derivative_window:
            raise ValueError(f"derivative_order {self.derivative_order} must be below derivative_window "
                             f"{self.derivative_window}")
        return self


class FitRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")

    model: Model
    experiments: list[Experiment] = Field(min_length=1, max_length=MAX_EXPERIMENTS)
    method: FitMethod = FitMethod.multiple_shooting
    options: FitOptions = Field(default_factory=FitOptions)

    @model_validator(mode="after")
    def _window_fits_the_records(self) -> "FitRequest":
        # only a window the user chose: the default quietly falls back to differences on short records
        if "derivative_window" in self.options.model_fields_set:
            for i, exp in enumerate(self.experiments):
                if self.options.derivative_window > len(exp.time):
                    raise ValueError(f"options.derivative_window {self.options.derivative_window} is longer than "
                                     f"experiments[{i}] ({len(exp.time)} samples); choose an odd window "
                                     "shorter than the record")
        return self


class ParameterEstimate(BaseModel):
    value: float
    stderr: Optional[float] = None
    ci95: Optional[tuple[float, float]] = None
    fixed: bool = False
    at_bound: Optional[Literal["lower", "upper"]] = None
    initial: float
    experiment: Optional[str] = Field(default=None, description="set for per_experiment copies")


class CovariancePublic(BaseModel):
    names: list[str]
    matrix: list[list[float]]


class FitMetrics(BaseModel):
    cost: float = Field(description="0.5 * sum of weighted squared residuals")
    ndata: int
    nfree: int
    nvarys: int
    rmse: dict[str, float]
    fit_percent: dict[str, float] = Field(description="NRMSE fit as MATLAB compare: 100(1-|y-ŷ|/|y-mean(y)|)")
    aic: float
    bic: float


class SolverInfo(BaseModel):
    method: FitMethod
    iterations: int
    wall_time_s: float
    return_status: str
    starts: int = 1
    derivative_filter: Optional[str] = None
    linear_in_parameters: Optional[bool] = None


class ResidualTest(BaseModel):
    """Whiteness (autocorrelation) or independence (cross-correlation with an input) test."""

    max_abs: float
    bound: float = Field(description="99% confidence band 2.58/sqrt(N)")
    lags: int
    passed: bool


class ResidualAnalysis(BaseModel):
    output: str
    rmse: float
    fit_percent: float
    autocorrelation: list[float]
    whiteness: ResidualTest
    cross_correlation: dict[str, list[float]] = Field(default_factory=dict)
    independence: dict[str, ResidualTest] = Field(default_factory=dict)


class ExperimentTrace(BaseModel):
    name: str
    time: list[float]
    simulated: dict[str, list[float]]
    residuals: dict[str, list[Optional[float]]]


class FitResult(BaseModel):
    """Outcome of one fit; `success: false` is a result, not an error."""

    success: bool
    status: str
    message: str
    parameters: dict[str, ParameterEstimate]
    covariance: Optional[CovariancePublic] = None
    covariance_note: Optional[str] = None
    correlation: Optional[CovariancePublic] = None
    initial_states: dict[str, dict[str, float]]
    metrics: FitMetrics
    solver: SolverInfo
    residual_analysis: list[ResidualAnalysis] = Field(default_factory=list)
    traces: Optional[list[ExperimentTrace]] = None
