"""Discovery: fit, trace the residual to a missing physical effect, add it, refit, report."""
from __future__ import annotations

from typing import Any, Literal, Optional, get_args

from pydantic import BaseModel, ConfigDict, Field

from greyfit.schemas.fit import FitRequest, FitResult
from greyfit.schemas.jobs import ON_FIRST_USE, job_create
from greyfit.schemas.model import Expression, Model, Name

# the families of solvers/screening/families, in the registry's order (schemas do not import
# solvers: tests/solvers/test_discovery_families.py checks the two agree)
Effect = Literal["coulomb", "quadratic_drag", "cubic_stiffness", "coupling_law", "offset", "sqrt_flow",
                 "radiation", "arrhenius", "saturable_rate", "saturation", "dead_zone", "output_offset",
                 "output_gain", "output_abs", "output_saturation", "power_law", "input_law", "parameter_law",
                 "parameter_step", "parameter_drift", "state_dependent", "input_delay", "sensor_lag",
                 "input_lag", "extra_pole", "hidden_store"]
ALL_EFFECTS: tuple[Effect, ...] = get_args(Effect)


class CustomCandidate(BaseModel):
    """A user term: `parameter * (term)` added to the equation of `equation`."""

    model_config = ConfigDict(extra="forbid")

    equation: Name = Field(description="the state whose equation the term enters")
    term: Expression = Field(
        description="the term added to that equation, an expression in states, inputs and `parameter`")
    parameter: Name = Field(description="the new parameter's name (it must not clash with the model's names)")
    value: float = Field(default=0.0, description="the new parameter's start value")
    lower: Optional[float] = Field(default=None, description="its lower bound (null: unbounded)")
    upper: Optional[float] = Field(default=None, description="its upper bound (null: unbounded)")


class DiscoveryOptions(BaseModel):
    model_config = ConfigDict(extra="forbid")

    max_terms: int = Field(default=3, ge=1, le=10, description="effects added at most (one per round)")
    effects: list[Effect] = Field(default_factory=lambda: list(ALL_EFFECTS),
                                  description="which library effects to try")
    candidates: list[CustomCandidate] = Field(
        default_factory=list, description="your own candidate terms, scored beside the library's effects")
    significance: float = Field(default=0.01, gt=0, lt=0.5,
                                description="family-wise level of the screening F-test (Bonferroni over candidates)")
    min_explained: float = Field(default=0.05, ge=0, lt=1,
                                 description="least fraction of an equation's residual variance a term must explain")
    min_bic_drop: float = Field(default=10.0, ge=0, description="least BIC drop of the confirming refit")
    min_t_value: float = Field(default=4.0, ge=0, description="least |value|/stderr of the new parameter")
    coulomb_epsilon: Optional[float] = Field(
        default=None, gt=0, description="tanh(v/ε) smoothing of sign(v); default: the refit chooses among "
                                        "0.1, 0.3, 1 and 3 % of the RMS of v")
    max_refits: int = Field(default=12, ge=1, le=50,
                            description="budget of confirming refits: rejected candidates and the contenders "
                                        "refitted against each other count too")
    time_budget_s: float = Field(
        default=300.0, gt=0, le=86_400,
        description="CPU-time budget of the search, in seconds of the process that runs it (the same work on a "
                    "quiet and on a loaded machine; the base fit always runs): no screen or refit starts "
                    "after it is spent, and a refit gets at most what is left as its max_cpu_time (and at most "
                    "a multiple of the base fit's CPU time, a contender a multiple of its leader's iterations); "
                    "the result says when the budget ended the search (`budget_exhausted`)")
    validation_tolerance: float = Field(
        default=0.01, ge=0, le=1,
        description="an effect is not kept if it raises the validation NRMSE of an output by more than this "
                    "(relative); only with validation experiments")


class DiscoverRequest(FitRequest):
    """A fit request plus `discovery`: fit, find the effect the model lacks, add it, refit."""
    model_config = ON_FIRST_USE

    discovery: DiscoveryOptions = Field(
        default_factory=DiscoveryOptions,
        description="the discovery options: effects to screen, terms to add, refit budget")


class ValidationSummary(BaseModel):
    model_config = ON_FIRST_USE
    rmse: dict[str, float] = Field(description="root-mean-square error per output on the validation records")
    fit_percent: dict[str, float] = Field(description="fit % per output on the validation records: 100 (1 - NRMSE)")
    nrmse: dict[str, float] = Field(
        description="normalised RMSE per output on the validation records: |y - ŷ| / |y - mean(y)|")


class FitSummary(BaseModel):
    model_config = ON_FIRST_USE
    success: bool = Field(default=True, description="whether the fit converged")
    status: str = Field(
        default="success", description="the fit's status: success or failed (or a more specific failure)")
    rmse: dict[str, Optional[float]] = Field(
        description="root-mean-square error per output on the estimation records (null where not finite)")
    fit_percent: dict[str, Optional[float]] = Field(
        description="fit % per output: 100 (1 - NRMSE) (null for a constant measured signal)")
    cost: Optional[float] = Field(description="null when the fit is not finite")
    aic: Optional[float] = Field(description="Akaike's information criterion (null when the fit is not finite)")
    bic: Optional[float] = Field(description="Bayesian information criterion (null when the fit is not finite)")
    white: dict[str, bool] = Field(description="residual whiteness test passed, per output")
    validation: Optional[ValidationSummary] = Field(
        default=None, description="simulation on the validation experiments (not used to fit)")


class CandidateScore(BaseModel):
    model_config = ON_FIRST_USE
    effect: str = Field(description="the effect's name in the library (e.g. cubic_stiffness)")
    equation: str = Field(description="the state equations the term enters, or 'output y' for the output path")
    term: str = Field(description="the term the effect adds, as an expression")
    explained_variance: float = Field(description="fraction of the residual variance the term explains at screening")
    bic_drop: float = Field(
        description="BIC of the residual regression without the term minus with it (positive: better)")
    p_value: float = Field(description="the term's p-value at screening (F test of the residual regression)")
    significant: bool = Field(description="whether the p-value is below the screen's Bonferroni level")
    scored_on: Literal["equations", "outputs", "refit"] = Field(
        description="equation residuals of measured states, output residuals through the sensitivities, or "
                    "'refit': the linearisation at this fit is blind to it (e.g. |h| where the fitted h keeps "
                    "its sign), so only a refit can judge it")
    record_specific: bool = Field(
        default=False, description="a change in time (step, drift): true of this record, it does not carry "
                                   "over to new data")


class Evidence(BaseModel):
    model_config = ON_FIRST_USE
    scored_on: Literal["equations", "outputs", "refit"] = Field(
        default="equations", description="what the screen scored the term on: equation residuals, output residuals, or"
                                         " only a refit")
    explained_variance: float = Field(description="fraction of the residual variance (equations or outputs) "
                                                  "the term explains at screening")
    screening_bic_drop: float = Field(description="the BIC drop of the term at screening")
    p_value: float = Field(description="the term's p-value at screening")
    bic_before: float = Field(description="BIC of the fit before the term was added")
    bic_after: float = Field(description="BIC of the refit with the term")
    bic_drop: float = Field(description="bic_before - bic_after (positive: the refit is better)")
    t_value: Optional[float] = Field(
        description="the new parameter's estimate over its standard error (null without a standard error)")
    refit_p_value: Optional[float] = Field(
        default=None,
        description="likelihood-ratio test of the refit against the model before, both output residuals "
                    "whitened by the AR noise model of the refit's residual (coloured noise is not evidence); "
                    "the effect is kept only if it is below the screen's Bonferroni level. null for "
                    "equation_error")
    noise_model_order: Optional[int] = Field(
        default=None, description="order of that AR noise model (BIC; 0: the residual is white)")
    residual_correlation_before: float = Field(
        description="correlation of the term with the output residual before the refit")
    residual_correlation_after: Optional[float] = Field(
        default=None, description="the same correlation with the refitted model's output residual; null where "
                                  "it is not defined (scored on states, or a constant residual or column)")


class NewParameter(BaseModel):
    model_config = ON_FIRST_USE
    name: str = Field(description="the added parameter's name")
    value: float = Field(description="its estimate")
    stderr: Optional[float] = Field(default=None, description="its standard error (null without a covariance)")
    ci95: Optional[tuple[float, float]] = Field(
        default=None, description="its confidence interval (null without a covariance)")
    unit: Optional[str] = Field(
        default=None, description="its unit, as the equation it enters implies from the model's units "
                                  "(null where they do not fix it)")


class RunnerUp(BaseModel):
    """A contender of the chosen effect, refitted against it on the same data."""
    model_config = ON_FIRST_USE

    effect: str = Field(description="the contender's effect name")
    equation: str = Field(description="the state equation its term enters")
    term: str = Field(description="the term it adds")
    delta_bic: Optional[float] = Field(
        description="its BIC minus the chosen one's, both output residuals whitened by one AR noise model "
                    "(coloured noise is not evidence), also when a gate rejected it after its refit converged; "
                    "null when it has no converged refit (it did not converge, or could not be built)")
    validation_nrmse: Optional[float] = Field(
        default=None, description="mean NRMSE over the outputs of the validation records; null without them")
    outcome: str = Field(description="why it was not chosen")


class DiscoveryStep(BaseModel):
    model_config = ON_FIRST_USE
    effect: str = Field(description="the effect added (its name in the library)")
    equation: str = Field(description="the state equation (or output) the term entered")
    term: str = Field(description="the term added, as an expression")
    description: str = Field(description="the effect in words (e.g. cubic (hardening or softening) stiffness on x)")
    parameters: list[NewParameter] = Field(description="the parameters the term added, with their estimates")
    evidence: Evidence = Field(description="why it was kept: screening score, refit BIC and likelihood-ratio test")
    after: FitSummary = Field(description="the fit with this term (and those before it)")
    record_specific: bool = Field(default=False, description="a change in time found in this record "
                                                             "(step, drift): it does not carry over to new data")
    verdict: Literal["identified", "ambiguous", "approximates"] = Field(
        default="identified",
        description="identified: better than every contender by refit (whitened BIC and validation); "
                    "ambiguous: a contender of another family explains these data as well (`runners_up`), "
                    "`separate_by` says what data would tell them apart; approximates (approximates; not "
                    "identified, the description says why): it moved the declared parameters far outside their "
                    "intervals before it, a stand-in; or it is a member of a series (a power, a smooth p(x)) that "
                    "won over a named law of the same variables; or its law explains much less of the learned "
                    "disturbance than a free smooth function of one variable")
    runners_up: list[RunnerUp] = Field(default_factory=list,
                                       description="the contenders refitted against it, best first")
    separate_by: Optional[str] = Field(default=None, description="for an ambiguous step: what would separate it "
                                                                 "from its runner-up")
    design: Optional[dict[str, Any]] = Field(
        default=None, description="for an ambiguous step: a DesignRequest body (POST /v1/designs, `greyfit design`) "
                                  "whose T-optimal input tells the step's law from the runners-up the data tie "
                                  "with; its limits, noise and length are the fitted record's, to be edited")


class RejectedCandidate(BaseModel):
    model_config = ON_FIRST_USE
    effect: str = Field(description="the candidate's effect name")
    equation: str = Field(description="the state equation its term would enter")
    term: str = Field(description="the term it would add")
    reason: Literal["evidence", "validation", "cpu_limit", "solver_failed", "refit_error", "superseded",
                    "parsimony", "shape"] = Field(
        description="evidence: the refit did not confirm it (BIC, t-value); validation: it made the "
                    "validation records worse; cpu_limit: the refit ran out of its CPU time (no verdict); "
                    "solver_failed / refit_error: the refit did not converge (within its iterations: a contender "
                    "gets a multiple of its leader's) or could not be built (no verdict); "
                    "superseded: kept at first, then explained by an effect added later and dropped; "
                    "parsimony: a catch-all (switch, step, drift, delay) that a named law explains as well, "
                    "that does not improve the validation records, that would pile a small coefficient onto an "
                    "accepted effect, or that moves the declared parameters far outside their intervals; "
                    "shape: the learned disturbance depends on more than the present value of any one variable "
                    "(e.g. a hysteresis) and the law removes too little of the residual's excess over the noise "
                    "to be more than a stand-in")
    detail: str = Field(description="the reason in words, with the numbers that decided it")


class DiscoveryResult(BaseModel):
    """Before and after, each effect added with its evidence, the candidates rejected, the final fit and model."""
    model_config = ON_FIRST_USE

    def report(self) -> str:
        """A text report for people (`greyfit ... --summary` prints it)."""
        from greyfit.schemas.text_report import discovery_report
        return discovery_report(self)

    def __str__(self) -> str:
        return self.report()

    conclusion: str = Field(description="one sentence: what was added, or why nothing was")
    before: FitSummary = Field(description="the declared model's fit")
    after: FitSummary = Field(description="the final model's fit")
    steps: list[DiscoveryStep] = Field(description="the effects added, in order, each with its evidence")
    rejected: list[RejectedCandidate] = Field(default_factory=list,
                                              description="candidates refitted and not kept, with the reason")
    screened: list[CandidateScore] = Field(description="the best-scoring candidates of the first round")
    notes: list[str] = Field(default_factory=list,
                             description="what was not tried and why (e.g. Coulomb on a state that keeps its sign)")
    model: Model = Field(description="the augmented model, ready to be sent again")
    added_inputs: dict[str, dict[str, list[Optional[float]]]] = Field(
        default_factory=dict, description="per experiment, input series the augmented model needs "
                                          "(an input delayed by whole samples); send them with the data")
    fit: FitResult = Field(description="the final fit")
    wall_time_s: float = Field(description="wall time of the whole discovery, in seconds")
    timings: dict[str, float] = Field(
        default_factory=dict,
        description="wall time per phase in seconds: base_fit, screening, refits (confirming and width "
                    "refits), validation (simulation of the validation records), other")
    budget_exhausted: bool = Field(
        default=False, description="the search stopped because `discovery.time_budget_s` was spent; what was "
                                   "found until then is reported")
    ambiguous: bool = Field(default=False, description="some step is `ambiguous`: another law explains these "
                                                      "data as well; see its runners_up and separate_by")
    discrepancy: Optional[Discrepancy] = Field(
        default=None, description="shape first: the missing term estimated at the declared model's fit without "
                                  "assuming its form; null where it could not be estimated (see notes)")
    unexplained: Optional[Unexplained] = Field(
        default=None, description="set when the final residual stays well above the noise: what is left, with "
                                  "its learned shape; null when the final model explains the records to the noise")


class DiscrepancyEquation(BaseModel):
    """The missing term of one equation (or output path) as the data show it, without a form assumed."""
    model_config = ON_FIRST_USE

    equation: str = Field(description="the state whose equation the disturbance d(t) enters, or 'output y' "
                                      "for the output path")
    log_likelihood: float = Field(description="of the output records with d a random walk (higher: the data "
                                              "prefer this equation for the missing term)")
    intensity: float = Field(description="the random walk's per-sample variance, in units of the noise variance "
                                         "and of d's scale (chosen by maximum likelihood: the smoothness penalty)")
    residual_share: float = Field(description="share of the weighted output residual's sum of squares that d "
                                              "removes")
    time: dict[str, list[float]] = Field(description="per experiment, the sample times of `samples`")
    samples: dict[str, list[float]] = Field(description="per experiment, d(t) in the equation's units "
                                                        "(state per time unit, or output units)")
    variable: Optional[str] = Field(default=None, description="the state, input or simple combination a smooth "
                                                              "function of which explains most of d")
    variable_samples: dict[str, list[float]] = Field(default_factory=dict,
                                                     description="per experiment, that variable at `time`")
    law_samples: dict[str, list[float]] = Field(
        default_factory=dict, description="per experiment, the fit to d at `time`: the smooth function of "
                                          "`variable` plus terms linear in the states and inputs (which the "
                                          "declared parameters can take up). Not a function of `variable` alone: "
                                          "to draw the law against it, use `law_grid` and `law_values`")
    law_grid: list[float] = Field(
        default_factory=list, description="values of `variable`, evenly spaced from its smallest sample to its "
                                          "largest (ascending); empty where no variable was related")
    law_values: list[float] = Field(
        default_factory=list, description="the smooth law at `law_grid`, in d's units: the part of the fit that "
                                          "depends on `variable` alone (the linear terms in the other states and "
                                          "inputs held at their means): the curve to draw over d against "
                                          "`variable`")
    share_explained: Optional[float] = Field(
        default=None, description="share of d's variance that smooth function explains (1: d is a function of "
                                  "`variable`; well below 1: it depends on more, e.g. on its history)")
    alternatives: dict[str, float] = Field(default_factory=dict,
                                           description="the next variables with their share explained")


class Discrepancy(BaseModel):
    """Shape first: a disturbance estimated on each equation in turn, the most likely first."""
    model_config = ON_FIRST_USE

    equations: list[DiscrepancyEquation] = Field(description="one per state equation and output path, the most "
                                                             "likely first")
    noise_level: dict[str, float] = Field(description="measurement-noise standard deviation per output, estimated "
                                                      "with the most likely disturbance")
    states: dict[str, dict[str, list[float]]] = Field(
        default_factory=dict, description="per experiment, the states (measured or not) the most likely "
                                          "disturbance implies, at its `time`")
    thinned_to: int = Field(description="series are thinned to at most this many samples per experiment")


class Unexplained(BaseModel):
    """What the final model does not explain: its residual stays well above the noise."""
    model_config = ON_FIRST_USE

    outputs: list[str] = Field(description="outputs whose residual stays above the noise")
    residual_to_noise: dict[str, float] = Field(description="final RMS residual over the estimated noise level")
    noise_level: dict[str, float] = Field(description="the estimated noise level per output")
    shape_share: float = Field(description="share of the final residual's sum of squares the learned shape holds")
    equation: str = Field(description="where the learned shape enters (the most likely disturbance)")
    variable: Optional[str] = Field(
        default=None, description="the variable a smooth function of which explains most of the shape (null: none "
                                  "does)")
    share_explained: Optional[float] = Field(default=None, description="share of the shape a smooth function of "
                                                                       "`variable` explains")
    message: str = Field(description="what is left unexplained, in words")
    shape: Discrepancy = Field(description="the disturbance learned at the final fit")


DiscoveryResult.model_rebuild()   # its shape fields name the classes above


DiscoverJobCreate = job_create("DiscoverJobCreate", DiscoverRequest, "A batch of discovery requests "
                               "(POST /v1/discover/jobs).")
