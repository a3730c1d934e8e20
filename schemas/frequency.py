"""Frequency-response fitting: transfer-function models, frequency data, options and the response result.

Polynomials are coefficient lists in descending powers of s; each coefficient is an expression of
the parameters and constants in the same whitelist grammar as ODE models.
"""
from __future__ import annotations

import math
from typing import Annotated, Literal, Optional, Union

from pydantic import BaseModel, ConfigDict, Discriminator, Field, Tag, field_validator, model_validator

from greyfit.schemas.jobs import job_create
from greyfit.schemas.limits import MAX_EXPERIMENTS, MAX_PARAMETERS, MAX_SAMPLES
from greyfit.schemas.model import RESERVED_NAMES, Expression, FiniteFloat, Model, Name, Parameter

MAX_DEGREE = 40
DEPRECATED_COSTS = {"seed_log": "log1p_abs_error"}   # old name -> the name that says what it is
Coefficients = list[Expression]


class Polynomials(BaseModel):
    """A transfer function num(s)/den(s) given by coefficients in descending powers of s."""

    model_config = ConfigDict(extra="forbid")

    num: Coefficients = Field(
        min_length=1, max_length=MAX_DEGREE + 1,
        description="numerator coefficients, descending powers of s (expressions in the parameters)")
    den: Coefficients = Field(
        description="denominator coefficients, descending powers of s", min_length=1, max_length=MAX_DEGREE + 1)


class Feedback(BaseModel):
    """A known controller C(s) closing the loop around the plant P(s) (negative feedback)."""

    model_config = ConfigDict(extra="forbid")

    controller: Polynomials = Field(description="C(s); its coefficients may use constants that each "
                                    "data set sets (e.g. Kp, Ki), so one structure serves every setting")
    measured: Literal["P/(1+PC)", "PC/(1+PC)"] = Field(
        default="P/(1+PC)", description="which closed-loop response the data are: plant output per "
        "input disturbance P/(1+PC), or plant output per reference PC/(1+PC)")


class TransferFunctionModel(BaseModel):
    """A plant P(s) = numerator/denominator, optionally measured inside a known feedback loop."""

    model_config = ConfigDict(extra="forbid")

    kind: Literal["transfer_function"] = Field(
        default="transfer_function", description="transfer_function: G(s) = numerator / denominator")
    name: Name = Field(default="plant", description="the model's name")
    parameters: list[Parameter] = Field(
        description="the parameters, with start values, bounds and units", min_length=1, max_length=MAX_PARAMETERS)
    constants: dict[Name, float] = Field(description="named constants the coefficients may use", default_factory=dict)
    numerator: Coefficients = Field(
        min_length=1, max_length=MAX_DEGREE + 1,
        description="numerator coefficients, descending powers of s (expressions in the parameters)")
    denominator: Coefficients = Field(
        description="denominator coefficients, descending powers of s", min_length=1, max_length=MAX_DEGREE + 1)
    constraints: list[Expression] = Field(
        description="expressions that must stay >= 0 at the estimates", default_factory=list, max_length=MAX_PARAMETERS)
    feedback: Optional[Feedback] = Field(
        default=None, description="the controller and loop the plant was measured in (null: open loop)")

    @model_validator(mode="after")
    def _names_are_consistent(self) -> "TransferFunctionModel":
        seen: dict[str, str] = {}
        for group, names in (("parameters", [p.name for p in self.parameters]),
                             ("constants", list(self.constants))):
            for name in names:
                if name in RESERVED_NAMES or name == "s":
                    raise ValueError(f"{group}: '{name}' is reserved (s, t, pi, e, inf); rename it")
                if name in seen:
                    raise ValueError(f"{group}: name '{name}' is already used in {seen[name]}")
                seen[name] = group
        for name, value in self.constants.items():
            if not math.isfinite(value):
                raise ValueError(f"constants.{name}: must be a finite number")
        return self


class OperatingPoint(BaseModel):
    """Where an ODE model is linearised: the inputs u0 and the states x0.

    `equilibrium: "solve"`: x0 is only the start of a Newton search; the point is the equilibrium
    f(x*, u0, θ) = 0 for every θ the fit tries (an implicit function of θ, differentiated exactly).
    `"given"`: x0 is the (measured) equilibrium itself; f(x0, u0, θ) = 0 becomes an equality
    constraint on θ (a row that no θ can satisfy is refused).
    """

    model_config = ConfigDict(extra="forbid")

    inputs: dict[Name, float] = Field(default_factory=dict, description="u0: a value for every model input")
    states: dict[Name, float] = Field(default_factory=dict, description="x0 (given) or the search start (solve)")
    equilibrium: Literal["solve", "given"] = Field(
        default="solve", description="solve: find the equilibrium at the given inputs; given: use the states as given")


class LinearisedOdeModel(Model):
    """The usual ODE model, linearised at an operating point: G(s) = C (sI − A)⁻¹ B + D.

    A = ∂f/∂x, B = ∂f/∂u, C = ∂h/∂x, D = ∂h/∂u at the operating point, as expressions of the
    parameters; `input` and `output` pick the channel the data measure (default: the only one).
    """

    kind: Literal["linearised_ode"] = Field(
        default="linearised_ode", description="linearised_ode: an ODE model linearised at an operating point")
    operating_point: OperatingPoint = Field(description="where the model is linearised")
    input: Optional[Name] = Field(default=None, description="the input the response is to")
    output: Optional[Name] = Field(default=None, description="the output measured")
    feedback: Optional[Feedback] = Field(
        default=None, description="the controller and loop the plant was measured in (null: open loop)")


def _model_kind(value) -> str:
    kind = value.get("kind") if isinstance(value, dict) else getattr(value, "kind", None)
    return kind if kind == "linearised_ode" else "transfer_function"


FrequencyModel = Annotated[Union[Annotated[TransferFunctionModel, Tag("transfer_function")],
                                 Annotated[LinearisedOdeModel, Tag("linearised_ode")]],
                           Discriminator(_model_kind)]


class SineTest(BaseModel):
    """A raw record with sinusoidal excitation at one or several frequencies (rad/s).

    The response at each frequency is estimated by least squares on sin/cos components of input
    and output (plus an offset), after discarding the transient before `settle_time`.
    """

    model_config = ConfigDict(extra="forbid", defer_build=True)

    omega: Union[float, list[float]] = Field(
        description="the test's angular frequency [rad/s] (or several, for a multisine)")
    time: list[float] = Field(description="sample times [s]", min_length=3, max_length=MAX_SAMPLES)
    input: list[float] = Field(description="the input measured at `time`", min_length=3, max_length=MAX_SAMPLES)
    output: list[float] = Field(description="the output measured at `time`", min_length=3, max_length=MAX_SAMPLES)
    settle_time: float = Field(default=0.0, ge=0, description="samples before this time are ignored")


class FrequencyData(BaseModel):
    """One measured frequency response: omega with real/imag, or gain with phase, or raw sine tests."""

    model_config = ConfigDict(extra="forbid", defer_build=True)

    name: Name = Field(default="data", description="the data set's name")
    omega: Optional[list[float]] = Field(default=None, max_length=MAX_SAMPLES,
                                         description="angular frequencies in rad/s, increasing")
    real: Optional[list[float]] = Field(
        default=None, max_length=MAX_SAMPLES,
        description="real part of the measured response at each frequency (with `imag`)")
    imag: Optional[list[float]] = Field(
        default=None, max_length=MAX_SAMPLES,
        description="imaginary part of the measured response at each frequency (with `real`)")
    gain: Optional[list[float]] = Field(
        default=None, max_length=MAX_SAMPLES,
        description="measured magnitude at each frequency (with `phase_deg`), linear")
    gain_unit: Literal["abs", "dB"] = Field(default="abs", description="gain as |G| or 20 log10 |G|")
    phase_deg: Optional[list[float]] = Field(
        description="measured phase at each frequency [deg] (with `gain`)", default=None, max_length=MAX_SAMPLES)
    sine_tests: Optional[list[SineTest]] = Field(
        default=None, max_length=10_000,
        description="time records of sine tests, one per frequency, from which the response is estimated")
    constants: dict[Name, FiniteFloat] = Field(
        default_factory=dict, description="values of model constants for this data set (e.g. Kp, Ki)")


class FrequencyFitOptions(BaseModel):
    """Cost, stability handling and solver options; every field has a default."""

    model_config = ConfigDict(extra="forbid", defer_build=True)

    cost: Literal["relative_complex", "complex", "log", "log1p_abs_error"] = Field(
        default="relative_complex",
        description="relative_complex: (Ĝ-G)/|G|; complex: Ĝ-G; log: log|Ĝ/G| and phase of Ĝ/G; "
                    "log1p_abs_error: log(|Ĝ-G|+1), the cost of the course notes on parameter estimation "
                    "from frequency data ('seed_log' is accepted as a deprecated alias)")
    stability: Literal["routh", "penalty", "check", "none"] = Field(
        default="routh", description="routh: Liénard-Chipart (Routh-Hurwitz) conditions of every closed-loop "
        "denominator as constraints >= stability_margin; penalty: their violation as an extra residual; "
        "check: poles reported only")
    stability_margin: float = Field(default=1e-6, ge=0, le=1,
                                    description="margin of each normalised Hurwitz condition")
    penalty_weight: float = Field(default=1e3, gt=0,
                                  description="weight of the stability violation residuals (stability: penalty)")
    also_stable_with: list[dict[Name, FiniteFloat]] = Field(
        default_factory=list, max_length=MAX_EXPERIMENTS,
        description="further constant settings (e.g. other controller gains) whose closed loop must be stable")
    levy_start: bool = Field(default=True, description="start from a Levy / Sanathanan-Koerner fit")
    sk_iterations: int = Field(default=5, ge=0, le=50, description="Sanathanan-Koerner reweightings")
    multistart: int = Field(default=1, ge=1, le=100, description="further starts drawn inside the bounds")
    seed: int = Field(default=0, description="random seed for the multistart draws")
    hessian: Literal["gauss_newton", "exact"] = Field(
        default="gauss_newton", description="Hessian Ipopt uses: gauss_newton (JᵀJ) or exact")
    max_iter: int = Field(default=500, ge=1, le=10_000, description="Ipopt iterations per start at most")
    max_cpu_time: float = Field(default=120.0, gt=0, le=86_400, description="CPU seconds for the whole fit")
    tol: float = Field(default=1e-10, gt=0, lt=1, description="Ipopt's convergence tolerance (tol)")
    confidence_level: float = Field(default=0.95, gt=0.5, lt=1,
                                    description="level of the confidence intervals (`ci95`)")

    @field_validator("cost", mode="before")
    @classmethod
    def _deprecated_cost_names(cls, value):
        return DEPRECATED_COSTS.get(value, value) if isinstance(value, str) else value


class FrequencyFitRequest(BaseModel):
    """A transfer-function (or linearised ODE) model and measured frequency responses (POST /v1/frequency-fits)."""

    model_config = ConfigDict(extra="forbid", defer_build=True)

    model: FrequencyModel = Field(
        description="a transfer function or a linearised ODE model, with its feedback loop if any")
    data: list[FrequencyData] = Field(
        min_length=1, max_length=MAX_EXPERIMENTS,
        description="the measured frequency responses, one data set per loop setting")
    options: FrequencyFitOptions = Field(
        description="cost, weighting, stability handling, solver options", default_factory=FrequencyFitOptions)


class LoopStability(BaseModel):
    """Poles of one fitted closed loop (the data set's, or one of `also_stable_with`)."""

    setting: str = Field(description="the loop setting (the data set's name, or the controller of also_stable_with)")
    poles_real: list[float] = Field(description="real parts of the closed loop's poles")
    poles_imag: list[float] = Field(description="imaginary parts of the closed loop's poles")
    max_real_part: Optional[float] = Field(
        description="null (and no poles, no Routh column) where the fitted loop's coefficients are not finite")
    stable: bool = Field(description="whether every pole has a negative real part")
    routh_first_column: list[float] = Field(description="the first column of the Routh array (all positive: stable)")


class DataSetResponse(BaseModel):
    """Measured and fitted response of one data set, for Bode and Nyquist plots."""

    name: str = Field(description="the data set's name")
    omega: list[float] = Field(description="the frequencies [rad/s]")
    measured_real: list[float] = Field(description="real part of the measured response")
    measured_imag: list[float] = Field(description="imaginary part of the measured response")
    fitted_real: list[float] = Field(description="real part of the fitted model's response")
    fitted_imag: list[float] = Field(description="imaginary part of the fitted model's response")
    zeros_real: list[float] = Field(description="real parts of the fitted closed loop's zeros")
    zeros_imag: list[float] = Field(description="imaginary parts of the fitted closed loop's zeros")
    numerator: list[float] = Field(description="fitted closed-loop numerator, descending powers of s")
    denominator: list[float] = Field(description="fitted closed-loop denominator, descending powers of s")


class FrequencyResponseResult(BaseModel):
    data: list[DataSetResponse] = Field(description="per data set, the measured and fitted responses")
    loops: list[LoopStability] = Field(description="per fitted closed loop, its poles and stability")
    stable: bool = Field(description="every fitted closed loop has all poles in the open left half plane")
    cost_kind: str = Field(description="options.cost of the fit: relative_complex, complex, log or log1p_abs_error")
    stability_handling: str = Field(description="options.stability of the fit: routh, penalty, check or none")
    levy_start: Optional[dict[str, float]] = Field(
        default=None, description="parameters of the linearised (Levy / Sanathanan-Koerner) start")
    operating_point: Optional[dict[str, float]] = Field(
        default=None, description="linearised ODE models: the states and inputs of the operating point "
                                  "at the fitted parameters")


FrequencyJobCreate = job_create("FrequencyJobCreate", FrequencyFitRequest,
                                "A batch of frequency-response fits (POST /v1/frequency-fits/jobs).")
