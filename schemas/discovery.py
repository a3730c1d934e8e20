"""Discovery: fit, trace the residual to a missing physical effect, add it, refit, report."""
from __future__ import annotations

from typing import Literal, Optional

from pydantic import BaseModel, ConfigDict, Field

from schemas.fit import FitRequest, FitResult
from schemas.model import Expression, Model, Name

Effect = Literal["coulomb", "quadratic_drag", "cubic_stiffness", "offset", "sqrt_flow", "saturation",
                 "parameter_step", "parameter_drift", "state_dependent", "input_delay"]
ALL_EFFECTS: tuple[str, ...] = ("coulomb", "quadratic_drag", "cubic_stiffness", "offset", "sqrt_flow",
                                "saturation", "parameter_step", "parameter_drift", "state_dependent",
                                "input_delay")


class CustomCandidate(BaseModel):
    """A user term: `parameter * (term)` added to the equation of `equation`."""

    model_config = ConfigDict(extra="forbid")

    equation: Name
    term: Expression
    parameter: Name
    value: float = 0.0
    lower: Optional[float] = None
    upper: Optional[float] = None


class DiscoveryOptions(BaseModel):
    model_config = ConfigDict(extra="forbid")

    max_terms: int = Field(default=3, ge=1, le=10)
    effects: list[Effect] = Field(default_factory=lambda: list(ALL_EFFECTS),
                                  description="which library effects to try")
    candidates: list[CustomCandidate] = Field(default_factory=list)
    significance: float = Field(default=0.01, gt=0, lt=0.5,
                                description="family-wise level of the screening F-test (Bonferroni over candidates)")
    min_explained: float = Field(default=0.05, ge=0, lt=1,
                                 description="least fraction of an equation's residual variance a term must explain")
    min_bic_drop: float = Field(default=10.0, ge=0, description="least BIC drop of the confirming refit")
    min_t_value: float = Field(default=4.0, ge=0, description="least |value|/stderr of the new parameter")
    coulomb_epsilon: Optional[float] = Field(
        default=None, gt=0, description="tanh(v/ε) smoothing of sign(v); default 1 % of the RMS of v")


class DiscoverRequest(FitRequest):
    discovery: DiscoveryOptions = Field(default_factory=DiscoveryOptions)


class FitSummary(BaseModel):
    rmse: dict[str, float]
    fit_percent: dict[str, float]
    cost: float
    aic: float
    bic: float
    white: dict[str, bool] = Field(description="residual whiteness test passed, per output")


class CandidateScore(BaseModel):
    effect: str
    equation: str
    term: str
    explained_variance: float
    bic_drop: float
    p_value: float
    significant: bool


class Evidence(BaseModel):
    explained_variance: float = Field(description="fraction of the equation residual variance the term explains")
    screening_bic_drop: float
    p_value: float
    bic_before: float
    bic_after: float
    bic_drop: float
    t_value: Optional[float]
    residual_correlation_before: float
    residual_correlation_after: float


class NewParameter(BaseModel):
    name: str
    value: float
    stderr: Optional[float] = None
    ci95: Optional[tuple[float, float]] = None


class DiscoveryStep(BaseModel):
    effect: str
    equation: str
    term: str
    description: str
    parameters: list[NewParameter]
    evidence: Evidence
    after: FitSummary


class DiscoveryResult(BaseModel):
    conclusion: str
    before: FitSummary
    after: FitSummary
    steps: list[DiscoveryStep]
    rejected: list[str] = Field(default_factory=list, description="candidates that failed the confirming refit")
    screened: list[CandidateScore] = Field(description="the best-scoring candidates of the first round")
    model: Model = Field(description="the augmented model, ready to be sent again")
    added_inputs: dict[str, dict[str, list[Optional[float]]]] = Field(
        default_factory=dict, description="per experiment, input series the augmented model needs "
                                          "(an input delayed by whole samples); send them with the data")
    fit: FitResult = Field(description="the final fit")
    wall_time_s: float
