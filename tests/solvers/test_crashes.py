"""Inputs that used to crash (issue 8, point 5): each is now a 422-class error naming the field,
or a result with success false and the reason; never a traceback."""
import copy
import json
import math

import numpy as np
import pytest
from pydantic import ValidationError

from greyfit.schemas import FitRequest
from greyfit.solvers.errors import DataError, ModelDefinitionError
from greyfit.solvers.fit import fit_model
from greyfit.solvers.model.expressions import compile_expression, parse, unparse
from tests.systems import msd_experiment, msd_model, simulate_msd

T = np.linspace(0, 5, 101)
GOOD = {"model": msd_model(), "experiments": [msd_experiment(T, simulate_msd(T), noise=0.002)],
        "method": "single_shooting"}


def changed(change):
    body = copy.deepcopy(GOOD)
    change(body)
    return body


def finite_json(result):
    """The result serialises to strict JSON (no NaN/Infinity anywhere)."""
    text = result.model_dump_json()
    json.loads(text, parse_constant=lambda c: pytest.fail(f"{c} in the result"))
    return text


@pytest.mark.parametrize("term, what", [
    ("1/0", "infinite"), ("1e308**2", "infinite"), ("(-1)^0.5", "not a real number"),
    ("log(0)", "infinite"), ("sqrt(-4)", "not a real number"), ("1e400", "too large"),
])
def test_constant_arithmetic_is_a_model_error(term, what):
    body = changed(lambda b: b["model"]["equations"].update(v=f"(u - c*v - k*x)/m + 1e-9*({term})"))
    with pytest.raises(ModelDefinitionError) as info:
        fit_model(FitRequest.model_validate(body))
    assert info.value.field == "equations.v" and what in str(info.value)


def test_constant_folding_keeps_finite_values():
    assert float(compile_expression("2^10 - 1/4 + max(1, 3)", {}, "w")) == 1024 - 0.25 + 3


def test_thousand_term_chain_compiles_and_round_trips():
    chain = "+".join(["v"] * 1000)
    node = parse(chain, "equations.v")
    assert unparse(node).count("v") == 1000
    body = changed(lambda b: b["model"]["equations"].update(v=f"(u - c*v - k*x)/m + 0*({chain})"))
    result = fit_model(FitRequest.model_validate(body))
    assert result.parameters["k"].value == pytest.approx(5.0, rel=0.01)


def test_one_free_parameter_on_a_tight_bound_with_given_initial_state():
    def change(b):
        b["model"]["parameters"][1].update(value=0.5, lower=0.45, upper=0.55)   # truth 0.8 outside
        b["model"]["parameters"][2].update(fixed=True, value=5.0)
        b["experiments"][0]["initial_state"] = {"x": 0.1, "v": 0.0}
    result = fit_model(FitRequest.model_validate(changed(change)))
    assert result.parameters["c"].at_bound == "upper"
    assert result.covariance is None and "bound" in result.covariance_note
    assert any(w.code == "parameter_at_bound" for w in result.warnings)
    finite_json(result)


@pytest.mark.parametrize("options, field", [
    ({"multistart": 3, "seed": -1}, "seed"),
    ({"output_weights": {"x": 1e300}}, "output_weights"),
    ({"output_weights": {"x": -1.0}}, "output_weights"),
    ({"output_weights": {"x": 0.0}}, "output_weights"),
])
def test_bad_options_are_validation_errors(options, field):
    with pytest.raises(ValidationError) as info:
        FitRequest.model_validate(changed(lambda b: b.update(options=options)))
    assert any(field in ".".join(map(str, e["loc"])) for e in info.value.errors())


def test_weight_that_overflows_with_the_data_names_the_weight():
    def change(b):
        b["experiments"][0]["outputs"]["x"][3] = 1e5
        b["options"] = {"output_weights": {"x": 1e99}}
    with pytest.raises(DataError) as info:
        fit_model(FitRequest.model_validate(changed(change)))
    assert info.value.field == "options.output_weights.x"


def test_extreme_weight_ratio_is_a_finite_result():
    body = changed(lambda b: b.update(options={"output_weights": {"x": 1e99}}))
    result = fit_model(FitRequest.model_validate(body))
    assert result.quality != "good" or result.covariance is not None
    finite_json(result)


def test_huge_output_sample_in_equation_error():
    def change(b):
        b["experiments"][0]["outputs"]["x"][5] = 1e308
        b["method"] = "equation_error"
    with pytest.raises(DataError) as info:
        fit_model(FitRequest.model_validate(changed(change)))
    assert info.value.field == "experiments[0].outputs.x" and "index 5" in str(info.value)


def test_cvodes_failing_on_a_rough_model_is_a_failed_result():
    def change(b):
        b["model"]["equations"]["v"] = "(u - c*v - k*x*exp(k*x*x*100))/m"
        b["model"]["parameters"][2].update(value=50.0)
        b["options"] = {"integrator": "cvodes", "max_iter": 20}
    result = fit_model(FitRequest.model_validate(changed(change)))
    assert result.success is False and result.quality == "failed"
    codes = {w.code for w in result.warnings}
    assert codes & {"simulation_failed", "non_finite_cost", "not_converged"}
    assert result.metrics.cost is None or math.isfinite(result.metrics.cost)
    finite_json(result)
