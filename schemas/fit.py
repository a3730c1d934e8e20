"""Fit request and the one documented fit result type (lmfit/scipy style)."""
from __future__ import annotations

import math
from enum import Enum
from typing import Annotated, Any, Literal, Optional, Union

from pydantic import BaseModel, ConfigDict, Discriminator, Field, Tag, field_validator, model_validator

from greyfit.schemas.experiment import Experiment
from greyfit.schemas.frequency import FrequencyResponseResult, LinearisedOdeModel, TransferFunctionModel
from greyfit.schemas.jobs import job_create
from greyfit.schemas.limits import MAX_EXPERIMENTS
from greyfit.schemas.model import Model, Name
from greyfit.schemas.online import MrasOptions, ParameterTrajectory, Prefilter, RlsOptions
from greyfit.schemas.preprocess import PreprocessingReport
from greyfit.schemas.validation import ValidationResult

# A weight squared times the data squared must stay far from overflow (1e308).
MIN_OUTPUT_WEIGHT, MAX_OUTPUT_WEIGHT = 1e-100, 1e100


class FitMethod(str, Enum):
    auto = "auto"   # requests only: a result names the method that ran (`solver.method_choice` says why)
    equation_error = "equation_error"
    single_shooting = "single_shooting"
    multiple_shooting = "multiple_shooting"
    frequency_response = "frequency_response"   # only in results of /v1/frequency-fits
    recursive_least_squares = "recursive_least_squares"
    mras = "mras"


class FitOptions(BaseModel):
    """Solver options; every field has a sensible default."""

    model_config = ConfigDict(extra="forbid")

    integrator: Literal["rk4", "cvodes"] = Field(
        default="rk4", description="rk4: fixed-step Runge-Kutta, `substeps` per sample interval; "
                                   "cvodes: adaptive implicit (BDF) integrator for stiff models")
    substeps: int = Field(
        default=1, ge=1, le=100,
        description="RK4 steps per sample interval; when not given, fits choose it from the model's "
                    "fastest mode along the simulation at the initial guess (|λ|h ≤ 0.25) and say so in "
                    "preprocessing.substeps")
    input_interpolation: Literal["auto", "foh", "zoh", "cubic"] = Field(
        default="auto", description="inputs between samples: linear (foh), held (zoh), a cubic through the "
                                    "samples (cubic: a smooth physical input; output-error fits read it on a "
                                    "grid 4 times finer), or auto: held where the input is piecewise constant "
                                    "(PRBS, steps, a digital controller's output), else linear, and refitted "
                                    "on the cubic reading where reading it as linear moves an estimate by "
                                    "0.3 standard errors or more")
    shooting_interval: int = Field(
        default=1, ge=1, le=10_000, description="samples per multiple-shooting interval")
    hessian: Literal["gauss_newton", "exact"] = Field(
        default="gauss_newton",
        description="Hessian Ipopt uses: gauss_newton (JᵀJ of the residuals, fast for least squares) or exact")
    max_iter: int = Field(default=200, ge=1, le=10_000, description="Ipopt iterations per start at most")
    max_cpu_time: float = Field(
        default=120.0, gt=0, le=86_400,
        description="CPU seconds for the whole fit; a further multistart start is begun only if it is "
                    "expected to end inside it")
    tol: float = Field(default=1e-8, gt=0, lt=1, description="Ipopt's convergence tolerance (tol)")
    multistart: int = Field(default=1, ge=1, le=100, description="starts drawn inside the bounds; best kept")
    seed: int = Field(default=0, ge=0, le=2**63 - 1,
                      description="random seed for multistart (a non-negative integer)")
    output_weights: dict[Name, float] = Field(
        default_factory=dict,
        description="weight per output; default 1/std of the measured output")
    derivative_window: int = Field(
        default=11, ge=5, le=1001,
        description="Savitzky-Golay window (odd, samples) for derivatives estimated by equation error")
    derivative_order: int = Field(default=3, ge=2, le=6, description="Savitzky-Golay polynomial order")
    return_traces: bool = Field(default=False, description="include simulated outputs and residuals")
    confidence_level: float = Field(
        default=0.95, gt=0.5, lt=1,
        description="level of the confidence intervals (`ci95`) and of the profile-likelihood intervals")
    robust_covariance: Literal["auto", "always", "never"] = Field(
        default="auto",
        description="HAC (Newey-West) covariance: when the whiteness test fails (auto), always, never")
    profile: list[Name] = Field(
        default_factory=list, max_length=20,
        description="free parameters to profile (profile-likelihood interval at confidence_level; "
                    "each costs a few dozen re-optimisations)")

    @field_validator("output_weights")
    @classmethod
    def _weights_are_positive_and_moderate(cls, weights: dict[str, float]) -> dict[str, float]:
        for name, w in weights.items():
            if not (math.isfinite(w) and MIN_OUTPUT_WEIGHT <= w <= MAX_OUTPUT_WEIGHT):
                raise ValueError(
                    f"output_weights.{name} = {w}: a weight must be a positive number between "
                    f"{MIN_OUTPUT_WEIGHT:g} and {MAX_OUTPUT_WEIGHT:g} (only ratios matter; to leave an "
                    "output out of the fit, leave its data out)")
        return weights
    rls: RlsOptions = Field(default_factory=RlsOptions, description="method recursive_least_squares")
    mras: MrasOptions = Field(default_factory=MrasOptions, description="method mras")
    prefilter: Optional[Prefilter] = Field(
        default=None, description="same low-pass on both sides of the equation (equation_error, RLS)")

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
    """A model, the records to fit it to, the method and its options (POST /v1/fits, `greyfit fit`)."""

    model_config = ConfigDict(extra="forbid")

    model: Model = Field(description="states, inputs, parameters with bounds, equations and outputs")
    experiments: list[Experiment] = Field(min_length=1, max_length=MAX_EXPERIMENTS,
                                          description="the records fitted; they share the parameters")
    method: FitMethod = Field(default=FitMethod.auto,
                              description="what is minimised: equation_error, single_shooting, multiple_shooting, "
                                          "or an online estimator (recursive_least_squares, mras); auto "
                                          "(default): single shooting where the model can be simulated from "
                                          "the start guess, else multiple shooting; `solver.method_choice` "
                                          "says which ran and why")
    options: FitOptions = Field(default_factory=FitOptions, description="solver options, each with a default")
    validation: list[Experiment] = Field(
        default_factory=list, max_length=MAX_EXPERIMENTS,
        description="records not used to fit; the result's `validation` has their simulation metrics")

    @field_validator("method")
    @classmethod
    def _time_domain_method(cls, method: FitMethod) -> FitMethod:
        if method == FitMethod.frequency_response:
            raise ValueError("frequency_response fits take a FrequencyFitRequest (model kind "
                             "transfer_function): POST /v1/frequency-fits")
        return method

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
    value: float = Field(description="the estimate (or the fixed value)")
    stderr: Optional[float] = Field(
        default=None, description="standard error (1 sigma); null without a covariance or for a fixed parameter")
    ci95: Optional[tuple[float, float]] = Field(
        default=None, description="confidence interval at the result's `confidence_level` (95 % unless "
        "options.confidence_level says otherwise; the name is kept for compatibility)")
    fixed: bool = Field(default=False, description="true when the parameter was held at its value")
    at_bound: Optional[Literal["lower", "upper"]] = Field(
        default=None, description="the bound the estimate ended at (lower or upper), else null")
    initial: float = Field(description="the start value the fit began from")
    experiment: Optional[str] = Field(default=None, description="set for per_experiment copies")
    stderr_classical: Optional[float] = Field(
        default=None, description="sigma^2 (J^T J)^-1 standard error; equals stderr unless the "
        "robust (HAC) covariance is reported")
    unit: Optional[str] = Field(default=None, description="the unit declared on the model's parameter")


class CovariancePublic(BaseModel):
    names: list[str] = Field(description="the estimated variables, in the order of the matrix's rows and columns")
    matrix: list[list[float]] = Field(description="the symmetric matrix, row by row")


class FitMetrics(BaseModel):
    """Null where undefined: a failed simulation, or a constant measured signal (fit %)."""

    cost: Optional[float] = Field(description="0.5 * sum of weighted squared residuals")
    ndata: int = Field(description="number of measured samples fitted (all outputs, all records)")
    nfree: int = Field(description="degrees of freedom: ndata - nvarys")
    nvarys: int = Field(description="number of estimated variables (free parameters and estimated initial states)")
    rmse: dict[str, Optional[float]] = Field(
        description="root-mean-square error per output (null where the simulation failed)")
    fit_percent: dict[str, Optional[float]] = Field(
        description="NRMSE fit as MATLAB compare: 100(1-|y-ŷ|/|y-mean(y)|)")
    aic: Optional[float] = Field(default=None, description="Akaike's information criterion, n ln(RSS/n) + 2k")
    bic: Optional[float] = Field(default=None, description="Bayesian information criterion, n ln(RSS/n) + k ln(n)")


class MethodChoice(BaseModel):
    """Which method a request with `method: auto` ran, and why."""

    requested: FitMethod = Field(description="the request's method (auto)")
    ran: FitMethod = Field(description="the method whose solution is reported (= `solver.method`)")
    reason: str = Field(description="why: what the simulation at the start guess showed, or why single "
                                    "shooting's answer was replaced by (or kept over) multiple shooting's")
    fallback: bool = Field(default=False, description="true when single shooting ran first and multiple "
                                                      "shooting was run after it (its answer failed or "
                                                      "fitted below the noise level)")


class SolverInfo(BaseModel):
    method: FitMethod = Field(description="the method that ran (never auto)")
    method_choice: Optional[MethodChoice] = Field(
        default=None, description="set when the request's method was auto: which method ran and why; "
        "null when the request named the method")
    iterations: int = Field(description="Ipopt iterations of the best start")
    wall_time_s: float = Field(description="wall time to the result in seconds, without the checks after the solve")
    return_status: str = Field(description="the solver's own status (e.g. Solve_Succeeded)")
    starts: int = Field(default=1, description="number of starts (multistart)")
    derivative_filter: Optional[str] = Field(
        default=None, description="equation error: how the state derivatives were estimated from the data")
    linear_in_parameters: Optional[bool] = Field(
        default=None, description="equation error: whether the problem was linear in the parameters (solved in one "
                                  "step)")
    compiled: Optional[bool] = Field(
        default=None, description="whether the per-sample model functions ran as compiled C (true: gcc's "
        "library, or on a new model's first fits the Tiny C Compiler's until gcc's is built) or in CasADi's "
        "interpreter (false); null where the method has no such functions")
    starts_at_best: Optional[int] = Field(
        default=None, description="multistart: how many starts reached the best cost (relative 1e-6); "
        "null for a single start")
    timings: dict[str, float] = Field(
        default_factory=dict, description="wall time of the whole call per stage, in seconds: prepare (compile "
        "the model, read the records, choose the method and substeps, build the problem), checks_before (the "
        "checks at the start guess and of the inputs), solve (Ipopt and the model's compiled "
        "functions, every start and retry), diagnostics (the Jacobian at the estimates, the residual analyses, "
        "the covariance, profiles), checks_after (the verdict: the input reading, the step check, the "
        "lack-of-fit screen), validation (the validation records' simulation), other; they add up to the "
        "call's wall time. wall_time_s is the time to the result without the checks after it")


class ResidualTest(BaseModel):
    """Whiteness (autocorrelation) or independence (cross-correlation with an input) test."""

    max_abs: float = Field(description="the largest |correlation| over the lags tested")
    bound: float = Field(description="per-lag band z/sqrt(N), z Šidák-corrected for the number of lags "
                                     "tested (3.54 for 25 lags at level 0.01); passed = max_abs <= bound")
    lags: int = Field(description="number of lags tested")
    passed: bool = Field(
        description="whether every lag is inside the family-wise band (white, or independent of the input)")
    p_value: Optional[float] = Field(None, description="family-wise p-value of max_abs (white residual: uniform)")
    level: float = Field(0.01, description="family-wise false-alarm rate of the test on a white residual")


class ResidualAnalysis(BaseModel):
    output: str = Field(description="the output's name")
    rmse: Optional[float] = Field(description="root-mean-square residual (null where not finite)")
    fit_percent: Optional[float] = Field(description="fit %: 100 (1 - NRMSE) (null for a constant measured signal)")
    autocorrelation: list[float] = Field(description="the residual's autocorrelation at lags 0, 1, ...")
    whiteness: ResidualTest = Field(description="the whiteness test of the autocorrelation")
    cross_correlation: dict[str, list[float]] = Field(
        description="per input, the residual's cross-correlation with it at lags 0, 1, ...", default_factory=dict)
    independence: dict[str, ResidualTest] = Field(
        description="per input, the independence test of that cross-correlation", default_factory=dict)


class ExperimentTrace(BaseModel):
    name: str = Field(description="the record's name")
    time: list[float] = Field(description="sample times [s]")
    simulated: dict[str, list[Optional[float]]] = Field(
        description="per output, the model's simulated output at `time` (null where not finite)")
    residuals: dict[str, list[Optional[float]]] = Field(
        description="per output, simulated minus measured (the solver's residual; null where a sample is "
                    "missing or not finite)")


class FitWarning(BaseModel):
    """Something the user should know about the result; `code` is stable (README lists them)."""

    code: str = Field(description="a stable machine-readable code (docs/trust.md lists them)")
    message: str = Field(description="what the warning means and what to do, in words")
    detail: dict[str, Any] = Field(description="the numbers behind it", default_factory=dict)


class ProfileInterval(BaseModel):
    """Profile likelihood of one parameter: the others re-optimised at each fixed value."""

    lower: Optional[float] = Field(description="null: the cost stays below `threshold` up to a bound "
                                   "or the step limit (the data do not bound the parameter there), or the "
                                   "profile was not computed (its CPU limit ran out; `note` says which)")
    upper: Optional[float] = Field(description="the interval's upper end; null as for `lower`")
    values: list[float] = Field(description="the parameter values visited, ascending")
    costs: list[Optional[float]] = Field(description="the re-optimised cost at each value")
    threshold: Optional[float] = Field(description="cost + ½ t²(ν) σ²: the interval is where the profile "
                                       "stays below it")
    note: Optional[str] = Field(
        default=None, description="why the profile is incomplete (a bound, the step limit, its CPU limit), else null")
    noise_adjustment: Optional[float] = Field(
        default=None, description="coloured residual (HAC covariance reported): the factor var_HAC/"
        "var_classical the threshold's ½t²σ² was scaled by; null: white residual, threshold unscaled")


def _result_model_kind(value) -> str:
    kind = value.get("kind") if isinstance(value, dict) else getattr(value, "kind", None)
    return kind if kind in ("transfer_function", "linearised_ode") else "ode"


# an ODE model has no `kind`; the frequency models say theirs
ResultModel = Annotated[Union[Annotated[Model, Tag("ode")],
                              Annotated[TransferFunctionModel, Tag("transfer_function")],
                              Annotated[LinearisedOdeModel, Tag("linearised_ode")]],
                        Discriminator(_result_model_kind)]


class AlternativeOptimum(BaseModel):
    """A converged multistart optimum whose cost the data cannot tell from the best one."""

    parameters: dict[str, float] = Field(description="the free parameters' values there")
    cost: float = Field(description="0.5 * sum of weighted squared residuals (the optimiser's objective)")
    starts: int = Field(description="how many starts converged to it (within 1 % in every parameter)")


class FitResult(BaseModel):
    """Outcome of one fit; `success: false` is a result, not an error."""

    success: bool = Field(description="whether the solver converged (see `quality` for whether to trust the answer)")
    status: str = Field(
        description="success, or failed (or a more specific failure); see `quality` for whether to trust the answer")
    message: str = Field(description="the solver's outcome in words")
    parameters: dict[str, ParameterEstimate] = Field(
        description="every parameter by name: estimate, standard error, interval, unit, initial value")
    confidence_level: float = Field(
        default=0.95, gt=0, lt=1,
        description="level of the parameters' confidence intervals (`ci95`): the request's "
        "options.confidence_level (0.95 where a result written by an older version does not say)")
    covariance: Optional[CovariancePublic] = Field(
        default=None, description="covariance of the estimated variables; null when it is not available (see "
                                  "covariance_note)")
    covariance_note: Optional[str] = Field(
        default=None, description="why there is no covariance (e.g. which combination is not identifiable), else null")
    correlation: Optional[CovariancePublic] = Field(
        default=None, description="correlation matrix of the estimated variables (null without a covariance)")
    initial_states: dict[str, dict[str, float]] = Field(
        description="per record, the initial state used (estimated or given)")
    metrics: FitMetrics = Field(description="data points, variables, cost, RMSE and fit % per output, AIC and BIC")
    solver: SolverInfo = Field(description="method, iterations, status, starts and timings of the solve")
    residual_analysis: list[ResidualAnalysis] = Field(
        description="per output, the residual's whiteness and independence tests", default_factory=list)
    traces: Optional[list[ExperimentTrace]] = Field(
        default=None, description="per record, simulated outputs and residuals (with options.return_traces), else null")
    validation: Optional[ValidationResult] = Field(
        default=None, description="simulation metrics on the request's validation records")
    preprocessing: Optional[PreprocessingReport] = Field(
        default=None, description="what each experiment's `preprocess` did, and hints about the data")
    frequency_response: Optional[FrequencyResponseResult] = Field(
        default=None, description="frequency fits: measured and fitted responses and the loops' stability; else null")
    warnings: list[FitWarning] = Field(
        default_factory=list, description="checks before and after the fit; codes in the README")
    quality: Literal["good", "suspect", "failed"] = Field(
        default="good", description="good: converged and no warning that doubts the answer; "
        "suspect: converged but a warning doubts it; failed: not converged or not finite")
    covariance_classical: Optional[CovariancePublic] = Field(
        default=None, description="sigma^2 (J^T J)^-1 when `covariance` holds the robust (HAC) one")
    active_constraints: list[str] = Field(
        default_factory=list, description="model.constraints that hold with equality at the solution")
    profile: Optional[dict[str, ProfileInterval]] = Field(
        default=None, description="profile-likelihood intervals of the parameters in options.profile")
    trajectory: Optional[ParameterTrajectory] = Field(
        default=None, description="θ(t) ± 2σ: online estimators and time-varying parameters")
    model: Optional[ResultModel] = Field(
        default=None, description="the model that was fitted (an ODE model, or the frequency fit's "
        "transfer function or linearised model): with `parameters` it is what `simulate` and `report` need "
        "to simulate again, so they do not need the request")
    alternative_optima: Optional[list[AlternativeOptimum]] = Field(
        default=None, description="multistart: the distinct converged optima (best first) whose cost "
        "exceeds the best by less than the profile-interval threshold ½ t²(ν) σ²; more than one makes "
        "the result suspect (warning multiple_optima); null for a single start")

    def report(self, *, min_correlation: float = 0.9) -> str:
        """A text report for people, like lmfit's `fit_report()`."""
        from greyfit.schemas.text_report import fit_report
        return fit_report(self, min_correlation=min_correlation)

    def __str__(self) -> str:
        return self.report()


JobCreate = job_create("JobCreate", FitRequest, "A batch of fits (POST /v1/jobs).")
