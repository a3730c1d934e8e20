"""Every class of bad input raises a clear error that names the field and says the fix."""
import copy
import math

import numpy as np
import pytest
from pydantic import ValidationError

from greyfit.schemas import FitRequest
from greyfit.solvers.errors import DataError, ModelDefinitionError
from greyfit.solvers.fit import fit_model
from tests.systems import msd_experiment, msd_model, simulate_msd

T = np.linspace(0, 5, 101)
GOOD = {"model": msd_model(), "experiments": [msd_experiment(T, simulate_msd(T))],
        "method": "single_shooting"}


def request_with(change):
    body = copy.deepcopy(GOOD)
    change(body)
    return body


def fails_with(body, error, *fragments):
    with pytest.raises(error) as info:
        fit_model(FitRequest.model_validate(body))
    for fragment in fragments:
        assert fragment in str(info.value), str(info.value)
    return info.value


def test_unknown_name_in_equation():
    body = request_with(lambda b: b["model"]["equations"].update(v="(u - c*v - kk*x)/m"))
    fails_with(body, ModelDefinitionError, "equations.v: unknown name 'kk' at column 12")


def test_unknown_name_in_output_and_definition():
    body = request_with(lambda b: b["model"].update(outputs={"x": "x + bias"}))
    fails_with(body, ModelDefinitionError, "outputs.x: unknown name 'bias'")
    body = request_with(lambda b: b["model"].update(definitions={"f": "c*vv"}))
    fails_with(body, ModelDefinitionError, "definitions.f: unknown name 'vv'")


def test_constraint_must_be_a_comparison_on_parameters():
    body = request_with(lambda b: b["model"].update(constraints=["c + k"]))
    fails_with(body, ModelDefinitionError, "constraints[0]", "comparison")
    body = request_with(lambda b: b["model"].update(constraints=["c*x >= 0"]))
    fails_with(body, ModelDefinitionError, "constraints[0]", "'x' is not one")


@pytest.mark.parametrize("change, fragment", [
    (lambda b: b["model"]["equations"].pop("v"), "no equation for state(s) ['v']"),
    (lambda b: b["model"]["equations"].update(w="1"), "['w'] are not states"),
    (lambda b: b["model"]["parameters"].append({"name": "x", "value": 1}), "name 'x' is already used"),
    (lambda b: b["model"]["parameters"][1].update(value=-1.0), "outside [lower, upper]"),
    (lambda b: b["model"]["parameters"][1].update(lower=5, upper=1, value=2), "swap them"),
    (lambda b: b["model"].update(states=["x", "v", "t"]), "'t' is reserved"),
    (lambda b: b["model"]["states"].append("2x"), "string_pattern_mismatch"),
    (lambda b: b["experiments"][0].update(time=[0.0]), "at least 2"),
    (lambda b: b.update(method="least_squares"), "equation_error"),
    (lambda b: b.update(options={"integrator": "euler"}), "rk4"),
])
def test_schema_refusals_name_the_field(change, fragment):
    body = request_with(change)
    with pytest.raises(ValidationError) as info:
        FitRequest.model_validate(body)
    text = str(info.value) + " ".join(e["type"] for e in info.value.errors())
    assert fragment in text, text


def test_time_must_increase():
    def change(b):
        b["experiments"][0]["time"][10] = b["experiments"][0]["time"][9]
    fails_with(request_with(change), DataError, "experiments[0].time", "time[10]", "increase strictly")


def test_length_mismatch_names_series_and_counts():
    body = request_with(lambda b: b["experiments"][0]["outputs"]["x"].pop())
    fails_with(body, DataError, "experiments[0].outputs.x: 100 values, time has 101")


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_values_are_refused(bad):
    """By the schema, at the sample (every path validates it: tests/service/test_nonfinite_every_path.py)."""
    for group, name, i in (("outputs", "v", 7), ("inputs", "u", 3)):
        body = copy.deepcopy(GOOD)
        body["experiments"][0][group][name][i] = bad
        with pytest.raises(ValidationError) as info:
            FitRequest.model_validate(body)
        assert [(e["type"], e["loc"]) for e in info.value.errors()] == [
            ("finite_number", ("experiments", 0, group, name, i))]


def test_missing_input_samples_and_missing_inputs():
    def change(b):
        b["experiments"][0]["inputs"]["u"][5] = None
    fails_with(request_with(change), DataError, "experiments[0].inputs.u", "null", "index 5")
    body = request_with(lambda b: b["experiments"][0]["inputs"].pop("u"))
    fails_with(body, DataError, "experiments[0].inputs.u", "no data for model input 'u'")
    body = request_with(lambda b: b["experiments"][0]["inputs"].update(z=[0.0] * 101))
    fails_with(body, DataError, "experiments[0].inputs.z", "not an input")


def test_output_without_data():
    def change(b):
        b["experiments"][0]["outputs"]["v"] = [None] * 101
    fails_with(request_with(change), DataError, "experiments[0].outputs.v", "every sample is null")
    body = request_with(lambda b: b["experiments"][0]["outputs"].pop("v"))
    fails_with(body, DataError, "outputs.v", "no data in any experiment")
    body = request_with(lambda b: b["experiments"][0]["outputs"].update(q=[0.0] * 101))
    fails_with(body, DataError, "experiments[0].outputs.q", "not an output")


def test_missing_output_samples_are_allowed_and_not_counted():
    def change(b):
        for i in range(0, 101, 2):
            b["experiments"][0]["outputs"]["v"][i] = None
    res = fit_model(FitRequest.model_validate(request_with(change)))
    assert res.success
    assert res.metrics.ndata == 101 + 50


def test_initial_state_and_derivatives_must_name_states():
    body = request_with(lambda b: b["experiments"][0].update(initial_state={"q": 0.0}))
    fails_with(body, DataError, "experiments[0].initial_state.q", "not a state")
    body = request_with(lambda b: b["experiments"][0].update(derivatives={"q": [0.0] * 101}))
    fails_with(body, DataError, "experiments[0].derivatives.q", "not a state")


def test_duplicate_experiment_names():
    body = request_with(lambda b: b["experiments"].append(copy.deepcopy(b["experiments"][0])))
    fails_with(body, DataError, "experiments[1].name", "used twice")
    # every parameter fixed is a simulation, not an error: tests/solvers/test_validation.py


def test_equation_error_needs_measured_states():
    body = request_with(lambda b: (b["experiments"][0]["outputs"].pop("v"),
                                   b["model"].update(outputs={"x": "x"}), b.update(method="equation_error")))
    fails_with(body, DataError, "experiments[0].outputs", "state 'v' has no output")
