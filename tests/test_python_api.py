"""greyfit from Python without JSON: the package docstring's example (a doctest), a model built with
greyfit.Model/Parameter fitted to the README's record read by Experiment.from_csv, fit's three ways of
taking a request, and a result that simulates and predicts on records."""
import doctest
import json
from pathlib import Path

import pytest

import greyfit

ROOT = Path(__file__).resolve().parents[1]
REQUEST = json.loads((ROOT / "examples" / "msd_request.json").read_text())


@pytest.fixture(scope="module")
def from_json():
    return greyfit.fit(greyfit.FitRequest.model_validate(REQUEST))


def test_the_package_docstring_example_runs():
    failures, tried = doctest.testmod(greyfit, optionflags=doctest.ELLIPSIS)
    assert tried >= 8 and failures == 0


def test_a_model_built_in_python_fits_the_readme_record_without_json(from_json):
    model = greyfit.Model(name="msd", states=["x", "v"], inputs=["u"],
                          parameters=[greyfit.Parameter("m", 2.0, lower=0.01, fixed=True),
                                      greyfit.Parameter("c", 0.3, lower=0, unit="N s/m"),
                                      greyfit.Parameter("k", 2.0, lower=0, unit="N/m")],
                          equations={"x": "v", "v": "(u - c*v - k*x)/m"})
    record = greyfit.Experiment.from_csv(ROOT / "examples" / "msd.csv", model)
    result = greyfit.fit(model=model, experiments=record, method="multiple_shooting", options={"substeps": 2})
    assert {k: p.value for k, p in result.parameters.items()} == {k: p.value for k, p in from_json.parameters.items()}
    assert result.parameters["c"].stderr == from_json.parameters["c"].stderr
    assert result.parameters["k"].unit == "N/m"
    # made with c = 0.8 N s/m, k = 5.0 N/m (m = 2 known): the truth inside the intervals
    assert result.parameters["c"].ci95[0] < 0.8 < result.parameters["c"].ci95[1]
    assert result.parameters["k"].ci95[0] < 5.0 < result.parameters["k"].ci95[1]


def test_fit_takes_a_request_its_dict_or_its_fields(from_json):
    assert isinstance(from_json, greyfit.FitResult)
    for result in (greyfit.fit(REQUEST), greyfit.fit(**REQUEST)):
        assert result.parameters == from_json.parameters and result.metrics == from_json.metrics
    with pytest.raises(TypeError, match="not both"):
        greyfit.fit(REQUEST, method="equation_error")


def test_the_result_simulates_and_predicts_on_records(from_json):
    record = REQUEST["experiments"][0]
    simulated = from_json.simulate(record)
    # multiple shooting: the fit's residual is the shooting one, equal to the simulation's within its gaps
    assert simulated.validation.rmse["x"] == pytest.approx(from_json.metrics.rmse["x"], rel=1e-4)
    predicted = from_json.predict(greyfit.Experiment(**record), horizon=3).experiments[0]
    assert predicted.horizon == 3 and len(predicted.predicted["x"]) == len(record["time"])
    new = greyfit.Experiment(time=record["time"], inputs=record["inputs"], initial_state={"x": 0.0, "v": 0.0})
    free = from_json.simulate(new).experiments[0]
    assert free.initial_state == {"x": 0.0, "v": 0.0} and len(free.outputs["x"]) == len(record["time"])
    loaded = greyfit.FitResult.model_validate_json(from_json.model_dump_json())   # a result read back simulates
    assert loaded.simulate(new).experiments[0].outputs == free.outputs
