"""The model: states, inputs, parameters with bounds, equations and outputs."""
from __future__ import annotations

import math
from typing import Annotated, Optional, Union

from pydantic import BaseModel, ConfigDict, Discriminator, Field, StringConstraints, Tag, model_validator

from greyfit.schemas.limits import (
    MAX_EXPRESSION_LENGTH,
    MAX_NAME_LENGTH,
    MAX_PARAMETERS,
    MAX_STATES,
    NAME_PATTERN,
)
from greyfit.schemas.online import (
    ArmaxTemplate,
    ArxTemplate,
    DiscreteTime,
    TimeVarying,
    expand_arx_template,
    template_kind,
)
from greyfit.schemas.templates import LinearStateSpace, expand_linear_state_space

Name = Annotated[str, StringConstraints(pattern=NAME_PATTERN, max_length=MAX_NAME_LENGTH)]
Expression = Annotated[str, StringConstraints(min_length=1, max_length=MAX_EXPRESSION_LENGTH)]
FiniteFloat = Annotated[float, Field(allow_inf_nan=False)]

RESERVED_NAMES = {"t", "pi", "e", "inf"}


class Parameter(BaseModel):
    """An unknown constant; `value` is the initial guess."""

    model_config = ConfigDict(extra="forbid")

    name: Name = Field(description="the name the expressions use")
    value: float = Field(allow_inf_nan=False,
                         description="the initial guess (the value, when fixed); inside the bounds")
    lower: Optional[float] = Field(default=None, allow_inf_nan=True, description="lower bound; omit for none")
    upper: Optional[float] = Field(default=None, allow_inf_nan=True, description="upper bound; omit for none")
    fixed: bool = Field(default=False, description="keep at `value` instead of estimating it")
    per_experiment: bool = Field(
        default=False, description="one copy per experiment, reported as name[experiment]")
    unit: Optional[str] = Field(default=None, max_length=32,
                                description="unit, e.g. \"N s/m\", shown with the estimate")
    time_varying: Optional[TimeVarying] = Field(
        default=None, description="estimate θ(t) (piecewise constant/linear) in batch fits")

    @model_validator(mode="after")
    def _bounds_hold_the_guess(self) -> "Parameter":
        lo = -math.inf if self.lower is None else self.lower
        hi = math.inf if self.upper is None else self.upper
        if math.isnan(lo) or math.isnan(hi):
            raise ValueError("lower/upper may not be NaN; omit them for no bound")
        if lo > hi:
            raise ValueError(f"lower ({lo}) is above upper ({hi}); swap them")
        if not lo <= self.value <= hi:
            raise ValueError(
                f"value {self.value} lies outside [lower, upper] = [{lo}, {hi}]; "
                "give an initial guess inside the bounds")
        return self


class Model(BaseModel):
    """A grey-box ODE model whose expressions use the whitelist grammar."""

    model_config = ConfigDict(extra="forbid")

    name: Name = Field(default="model", description="a label for the model")
    states: list[Name] = Field(min_length=1, max_length=MAX_STATES, description="state names")
    inputs: list[Name] = Field(default_factory=list, max_length=MAX_STATES, description="input names (may be empty)")
    parameters: list[Parameter] = Field(default_factory=list, max_length=MAX_PARAMETERS,
                                        description="the unknowns (and fixed values), with bounds")
    constants: dict[Name, float] = Field(default_factory=dict, description="named numbers")
    definitions: dict[Name, Expression] = Field(
        default_factory=dict, description="intermediate quantities, in order; usable by later expressions")
    equations: dict[Name, Expression] = Field(description="dx/dt of every state (x[k+1] when discrete)")
    outputs: Optional[dict[Name, Expression]] = Field(
        default=None, description="what each measured series is; default: every state measured as itself")
    constraints: list[Expression] = Field(default_factory=list, max_length=MAX_PARAMETERS,
                                          description="inequalities on parameters, e.g. \"a1*a2 - a3 >= 0\"")
    linear_state_space: Optional[LinearStateSpace] = Field(
        default=None, description="ẋ = Ax + Bu, y = Cx + Du with entries numbers, parameter names or "
                                  "expressions; expanded into equations and outputs")

    @model_validator(mode="before")
    @classmethod
    def _expand_linear_template(cls, data):
        """Fill equations/outputs from linear_state_space; a round trip (both given) must agree."""
        if not isinstance(data, dict) or data.get("linear_state_space") is None:
            return data
        lss = LinearStateSpace.model_validate(data["linear_state_space"])
        equations, outputs = expand_linear_state_space(lss, list(data.get("states") or []),
                                                       list(data.get("inputs") or []))
        given = data.get("equations")
        if given is not None and dict(given) != equations:
            raise ValueError("give either equations or linear_state_space, not both")
        if data.get("outputs") is not None and outputs is not None and dict(data["outputs"]) != outputs:
            raise ValueError("give either outputs or linear_state_space.C/D, not both")
        return {**data, "equations": equations, "outputs": outputs if outputs is not None else data.get("outputs")}

    discrete: Optional[DiscreteTime] = Field(
        default=None, description="difference equations: equations[x] is x[k+1]")
    template: Optional[Annotated[Union[Annotated[ArxTemplate, Tag("arx")], Annotated[ArmaxTemplate, Tag("armax")]],
                                 Discriminator(template_kind)]] = Field(
        default=None, description="ARX or ARMAX template expanded into states/equations (needs discrete)")

    @model_validator(mode="before")
    @classmethod
    def _expand_template(cls, data):
        if isinstance(data, dict) and data.get("template") is not None and not data.get("states"):
            return expand_arx_template(data)
        return data

    @model_validator(mode="after")
    def _names_are_consistent(self) -> "Model":
        groups = {
            "states": list(self.states),
            "inputs": list(self.inputs),
            "parameters": [p.name for p in self.parameters],
            "constants": list(self.constants),
            "definitions": list(self.definitions),
        }
        seen: dict[str, str] = {}
        for group, names in groups.items():
            for name in names:
                if name in RESERVED_NAMES:
                    raise ValueError(f"{group}: '{name}' is reserved (t, pi, e, inf); rename it")
                if name in seen:
                    raise ValueError(
                        f"{group}: name '{name}' is already used in {seen[name]}; names must be unique")
                seen[name] = group
        missing = [s for s in self.states if s not in self.equations]
        if missing:
            raise ValueError(f"equations: no equation for state(s) {missing}; give d/dt of every state")
        extra = [k for k in self.equations if k not in self.states]
        if extra:
            raise ValueError(f"equations: {extra} are not states; equations are keyed by state name")
        for name, value in self.constants.items():
            if not math.isfinite(value):
                raise ValueError(f"constants.{name}: must be a finite number")
        return self

    units: dict[Name, Annotated[str, StringConstraints(max_length=32)]] = Field(
        default_factory=dict, description="units of states, inputs, outputs and of time (key `t`), e.g. "
        "{\"x\": \"m\", \"t\": \"s\"}: the report's axes and tables show them (parameters carry their own `unit`)")

    @model_validator(mode="after")
    def _units_name_something(self) -> "Model":
        known = {"t", *self.states, *self.inputs, *(self.outputs or {})}
        unknown = sorted(set(self.units) - known)
        if unknown:
            raise ValueError(f"units: '{unknown[0]}' is not a state, input, output or t; units are keyed by "
                             f"those names (parameters carry their own `unit`)")
        return self

    def measured_outputs(self) -> dict[str, str]:
        """Output equations, defaulting to every state measured as itself."""
        return dict(self.outputs) if self.outputs is not None else {s: s for s in self.states}
