"""Contract of the online and time-varying estimators: discrete-time models, ARX templates,
time-varying parameters, RLS / MRAS / prefilter options and the parameter trajectory they return.

Kept apart from `schemas.model` and `schemas.fit` (which import from here) so that those shared
files only gain a field each.
"""
from __future__ import annotations

from typing import Annotated, Literal, Optional

from pydantic import AliasChoices, BaseModel, ConfigDict, Field, StringConstraints, model_validator

from greyfit.schemas.limits import MAX_NAME_LENGTH, NAME_PATTERN

_Name = Annotated[str, StringConstraints(pattern=NAME_PATTERN, max_length=MAX_NAME_LENGTH)]


# --- model side --------------------------------------------------------------------------------
class DiscreteTime(BaseModel):
    """The model is a difference equation: `equations[x]` is x[k+1] = f(x[k], u[k], θ, t_k)."""

    model_config = ConfigDict(extra="forbid", populate_by_name=True)

    sample_time: float = Field(gt=0, validation_alias=AliasChoices("sample_time", "Ts"),
                               description="Ts [s]; the experiments' time must step by exactly Ts")


class ArxTemplate(BaseModel):
    """ARX template y[k] = -a1 y[k-1] - ... - a_na y[k-na] + b1 u[k-nk] + ... + b_nb u[k-nk-nb+1].

    Expanded into the discrete-time contract: the output state `output`, delay states
    `<output>_1..` and `<input>_1..` (reconstructed from the data by equation error) and the
    parameters a1..a_na, b1..b_nb (declare them yourself to give guesses or bounds).
    """

    model_config = ConfigDict(extra="forbid")

    kind: Literal["arx"] = Field(default="arx", description="arx: A(q) y = B(q) u + e")
    na: int = Field(description="order of A (past outputs)", ge=1, le=20)
    nb: int = Field(description="order of B (past inputs)", ge=1, le=20)
    nk: int = Field(default=1, ge=1, le=50, description="input delay in samples (>= 1)")
    output: _Name = Field(default="y", description="the output's name")
    input: _Name = Field(default="u", description="the input's name")


def expand_arx_template(data: dict) -> dict:
    """Fill states, inputs, equations, outputs and parameters of a model dict from its template."""
    raw = data["template"]
    kind = template_kind(raw)
    tpl = (ArmaxTemplate if kind == "armax" else ArxTemplate).model_validate(raw)
    if data.get("states") or data.get("equations"):
        raise ValueError("template: give either a template or states/equations, not both")
    if data.get("discrete") is None:
        raise ValueError(f"template: an {kind.upper()} model is discrete time; add discrete: {{sample_time: Ts}}")
    if isinstance(tpl, ArmaxTemplate):
        if data.get("inputs") not in (None, [], [tpl.input]):
            raise ValueError(f"template: the ARMAX model's inputs are [{tpl.input}] (and the measured output)")
        return _expand_armax(data, tpl)
    y, u = tpl.output, tpl.input
    y_lags = [f"{y}_{i}" for i in range(1, tpl.na)]
    u_lag_max = tpl.nk - 1 + tpl.nb - 1
    u_lags = [f"{u}_{i}" for i in range(1, u_lag_max + 1)]

    def u_at(lag: int) -> str:
        return u if lag == 0 else f"{u}_{lag}"

    terms = [f"- a{i}*{y if i == 1 else y_lags[i - 2]}" for i in range(1, tpl.na + 1)]
    terms += [f"+ b{j}*{u_at(tpl.nk - 1 + j - 1)}" for j in range(1, tpl.nb + 1)]
    equations = {y: " ".join(terms)}   # "- a1*y - a2*y_1 + b1*u_0 ..." (leading unary minus)
    for i, name in enumerate(y_lags):
        equations[name] = y if i == 0 else y_lags[i - 1]
    for i, name in enumerate(u_lags):
        equations[name] = u if i == 0 else u_lags[i - 1]
    declared = {p["name"]: p for p in data.get("parameters") or []}
    names = [f"a{i}" for i in range(1, tpl.na + 1)] + [f"b{j}" for j in range(1, tpl.nb + 1)]
    unknown = sorted(set(declared) - set(names))
    if unknown:
        raise ValueError(f"template: parameter '{unknown[0]}' is not part of the ARX template ({names})")
    out = dict(data)
    out.update(states=[y, *y_lags, *u_lags], inputs=data.get("inputs") or [u], equations=equations,
               outputs=data.get("outputs") or {y: y},
               parameters=[declared.get(n, {"name": n, "value": 0.0}) for n in names])
    return out


class ArmaxTemplate(BaseModel):
    """ARMAX template A(q) y = B(q) u + C(q) e, fitted by prediction error.

    A = 1 + a1 q⁻¹ + … + a_na q⁻ⁿᵃ, B = b1 q⁻ⁿᵏ + … + b_nb q⁻⁽ⁿᵏ⁺ⁿᵇ⁻¹⁾, C = 1 + c1 q⁻¹ + … + c_nc q⁻ⁿᶜ,
    e white. Expanded into the one-step predictor ŷ = (1 − A/C) y + (B/C) u in observer canonical
    form, n = max(na, nk + nb − 1, nc) states `<output>_x1..` (x1 = ŷ):

        x_i[k+1] = x_{i+1}[k] − c_i x1[k] + (c_i − a_i) y[k] + b̃_i u[k],   ŷ[k] = x1[k],

    driven by the measured output (input `<output>_measured`, read from the experiment's output
    `<output>`). Output error on this model (single or multiple shooting) minimises Σ (y − ŷ)²: the
    prediction-error method, with the n initial states estimated. The predictor is stable when C's
    roots lie inside the unit circle.
    """

    model_config = ConfigDict(extra="forbid")

    kind: Literal["armax"] = Field(default="armax", description="armax: A(q) y = B(q) u + C(q) e")
    na: int = Field(description="order of A (past outputs)", ge=1, le=20)
    nb: int = Field(description="order of B (past inputs)", ge=1, le=20)
    nc: int = Field(description="order of C (past noise)", ge=1, le=20)
    nk: int = Field(default=1, ge=1, le=50, description="input delay in samples (>= 1)")
    output: _Name = Field(default="y", description="the output's name")
    input: _Name = Field(default="u", description="the input's name")


def template_kind(value) -> str:
    """'arx' (the default when kind is left out) or 'armax'."""
    kind = value.get("kind", "arx") if isinstance(value, dict) else getattr(value, "kind", "arx")
    return "armax" if kind == "armax" else "arx"


def measured_output_inputs(template) -> dict[str, str]:
    """Inputs that carry a measured output (ARMAX predictor): input name -> output name."""
    if isinstance(template, ArmaxTemplate):
        return {f"{template.output}_measured": template.output}
    return {}


def _expand_armax(data: dict, tpl: ArmaxTemplate) -> dict:
    y, u = tpl.output, tpl.input
    n = max(tpl.na, tpl.nk + tpl.nb - 1, tpl.nc)
    x = [f"{y}_x{i}" for i in range(1, n + 1)]
    y_in = f"{y}_measured"
    equations = {}
    for i in range(1, n + 1):
        terms = [x[i]] if i < n else []
        a = f"a{i}" if i <= tpl.na else None
        c = f"c{i}" if i <= tpl.nc else None
        if c:
            terms.append(f"- {c}*{x[0]}")
        if a or c:
            terms.append(f"+ ({c or 0} - {a or 0})*{y_in}")
        j = i - tpl.nk + 1                      # b_j multiplies u[k-i] in the q⁻ⁱ coefficient
        if 1 <= j <= tpl.nb:
            terms.append(f"+ b{j}*{u}")
        equations[x[i - 1]] = " ".join(terms).lstrip("+ ") or "0"
    names = ([f"a{i}" for i in range(1, tpl.na + 1)] + [f"b{j}" for j in range(1, tpl.nb + 1)]
             + [f"c{i}" for i in range(1, tpl.nc + 1)])
    declared = {p["name"]: p for p in data.get("parameters") or []}
    unknown = sorted(set(declared) - set(names))
    if unknown:
        raise ValueError(f"template: parameter '{unknown[0]}' is not part of the ARMAX template ({names})")
    out = dict(data)
    out.update(states=x, inputs=[u, y_in], equations=equations, outputs={y: x[0]},
               parameters=[declared.get(nm, {"name": nm, "value": 0.0}) for nm in names])
    return out


class TimeVarying(BaseModel):
    """A parameter estimated as a trajectory θ(t) in a batch fit.

    `piecewise_constant`: one value per segment; `piecewise_linear`: one value per knot, linear in
    between. Knots are given, or `segments` equal segments span the experiments' time range.
    `total_variation` adds weight·Σ|Δ| (first differences of the values for piecewise constant,
    of the slopes for piecewise linear, relative to the parameter's guess) as extra residual rows,
    which keeps steps sharp and trajectories free of spurious wiggles.
    """

    model_config = ConfigDict(extra="forbid")

    kind: Literal["piecewise_constant", "piecewise_linear"] = Field(
        default="piecewise_constant", description="piecewise_constant or piecewise_linear in time")
    knots: Optional[list[float]] = Field(
        default=None, min_length=2, max_length=2000,
        description="the times [s] where the pieces meet (or give `segments`)")
    segments: Optional[int] = Field(
        description="number of equal pieces over the record (or give `knots`)", default=None, ge=1, le=2000)
    regularization: Literal["total_variation", "none"] = Field(
        default="total_variation", description="total_variation: penalise changes between pieces; none")
    weight: float = Field(default=1e-3, ge=0, le=1e6,
                          description="total-variation weight per data residual row")

    @model_validator(mode="after")
    def _knots_or_segments(self) -> "TimeVarying":
        if (self.knots is None) == (self.segments is None):
            raise ValueError("give either knots (times) or segments (a count)")
        if self.knots is not None and any(b <= a for a, b in zip(self.knots, self.knots[1:])):
            raise ValueError("knots must increase strictly")
        return self


# --- fit side ------------------------------------------------------------------------------------
class RlsOptions(BaseModel):
    """Recursive least squares (model reference adaptive systems chapter, eqs. 7-38/39 and 7-44/45)."""

    model_config = ConfigDict(extra="forbid")

    forgetting: float = Field(default=0.99, gt=0, le=1, description="λ (λ1 of the gain laws)")
    gain_law: Literal["forgetting", "decreasing_gain", "constant_trace", "constant_gain"] = Field(
        default="forgetting",
        description="forgetting: weighted LS with λ (7-38); decreasing_gain: λ = 1, ordinary LS; "
                    "constant_trace: λ1(k) keeps trace P constant (7-45, λ2 = λ1); "
                    "constant_gain: P stays γI (λ1 = 1, λ2 = 0)")
    initial_covariance: float = Field(default=1e4, gt=0, le=1e12,
                                      description="γ in P₀ = γI (parameters scaled by their guesses); with "
                                                  "initialisation 'exact' it serves only the first rows")
    trajectory_every: int = Field(default=1, ge=1, le=100_000,
                                  description="keep every n-th sample of θ(t) in the result")
    noise: Literal["equation", "measurement"] = Field(
        default="equation",
        description="what the ±2σ band assumes: equation: white equation error; measurement: white noise on "
                    "the measured output of a discrete-time model, which makes the equation error a moving "
                    "average (taken from the model at the current estimate)")
    initialisation: Literal["exact", "prior"] = Field(
        default="exact",
        description="exact: once the first rows' information matrix is invertible, start from their "
                    "weighted least-squares solution and P = (Σ λ^(k-i) ΦᵀΦ)⁻¹, so that λ = 1 gives batch "
                    "least squares; prior: P₀ = γI around the guess throughout (pulls poorly excited "
                    "directions towards the guess). Forgetting and decreasing-gain laws only")


class MrasOptions(BaseModel):
    """Model-reference adaptive estimator (model reference adaptive systems chapter, 7.3), PI law (7-29/30)."""

    model_config = ConfigDict(extra="forbid")

    kp: float = Field(default=0.0, ge=0, description="proportional adaptation gain (>= 0)")
    ki: float = Field(default=1000.0, gt=0, description="integral adaptation gain [1/s] (> 0), on normalised signals")
    substeps: int = Field(default=1, ge=1, le=100, description="integrator steps of the adjustable model per sample "
                                                                    "(RK4 unless options.integrator is cvodes)")
    trajectory_every: int = Field(default=1, ge=1, le=100_000,
                                  description="keep every n-th sample of θ(t) in the result")


class Prefilter(BaseModel):
    """The same stable low-pass on both sides of the equation (state-variable filter; Robust parameter
    estimation by noise reduction).

    Continuous-time models: n cascaded first-order filters ω/(s+ω) on states and inputs; the
    derivative of the filtered state comes from the filter itself, ω(F^{n-1}x − F^n x), so no
    differentiation of noisy data is needed. Discrete-time models: the noise-reduction paper's
    H_f = (1−a_f)/(1 − a_f z⁻¹), a_f = exp(−2π f_c Ts), n times, on outputs and inputs.
    The first 5 time constants are dropped (filter start-up).
    """

    model_config = ConfigDict(extra="forbid")

    kind: Literal["lowpass"] = Field(default="lowpass", description="the filter: a low-pass (the only kind)")
    cutoff_hz: float = Field(gt=0, description="cut-off frequency f_c [Hz]")
    order: int = Field(default=1, ge=1, le=4, description="number of cascaded first-order filters")


class ExcitationReport(BaseModel):
    """Persistent excitation over the window the estimator used."""

    window_samples: int = Field(description="effective memory: 1/(1-λ), or the record")
    input_order: dict[str, int] = Field(description="PE order of each input over the window")
    regressor_rank: int = Field(description="rank of the regressor matrix over the window")
    regressor_size: int = Field(description="number of regressors (columns)")
    regressor_condition: Optional[float] = Field(
        default=None, description="condition number of the regressor matrix (null where singular)")
    persistently_exciting: bool = Field(description="the regressor has full rank over the window and, for "
                                        "models linear in states and inputs, the inputs' PE order reaches "
                                        "required_order")
    required_order: Optional[int] = Field(
        default=None, description="PE order the model needs: the most coefficients one equation estimates "
                                  "(an n-th order plant: 2n, i.e. n frequencies); null for nonlinear regressors")
    available_order: Optional[int] = Field(
        default=None, description="PE order the inputs give the regression over the window (plus one for an "
                                  "offset term)")


class ParameterTrajectory(BaseModel):
    """θ(t) with a ±2σ band: from an online estimator or a declared time-varying parameter."""

    estimator: str = Field(description="the estimator (rls, mras, time_varying, ...)")
    time: list[float] = Field(description="sample times [s]")
    values: dict[str, list[Optional[float]]] = Field(
        description="per parameter, its estimate at each time (null when unknown)")
    lower: dict[str, list[Optional[float]]] = Field(description="value − 2σ (null when unknown)")
    upper: dict[str, list[Optional[float]]] = Field(description="value + 2σ (null when unknown)")
    coefficients: Optional[dict[str, list[Optional[float]]]] = Field(
        default=None, description="the linear coefficients actually estimated, when the physical "
                                  "parameters are mapped from them")
    mapping: Optional[dict[str, str]] = Field(
        default=None, description="coefficient -> its expression in the physical parameters")
    excitation: Optional[ExcitationReport] = Field(
        default=None, description="persistent excitation over the estimator's window")
    note: Optional[str] = Field(
        default=None, description="a remark on the trajectory (e.g. the estimator's warm-up), else null")
    outside_bounds: Optional[dict[str, list[bool]]] = Field(
        default=None, description="online estimators, per parameter with declared bounds and per sample of "
                                  "`time`: true where the estimate is outside them (no physical pre-image, "
                                  "e.g. R < 0)")
