"""Frequency-response fits through the HTTP API and the CLI."""
import json

import numpy as np
import pytest

from greyfit.service.cli.commands import main as cli_main
from tests.frequency_systems import NAMES, TRUTH, frequency_data, seed001_model, sine_records
from tests.service.conftest import assert_problem

GUESS = {n: 1.5 * v for n, v in TRUTH.items()}


def test_raw_sine_tests_to_fit_end_to_end(client):
    """Sine-test records (1 % output noise) -> G(jω) by sin/cos least squares -> fit, over HTTP."""
    omegas = np.logspace(-1, 3, 20)
    body = {"model": seed001_model(GUESS),
            "data": [{"name": "pi", "sine_tests": sine_records(TRUTH, 1, 1, omegas, noise=0.01, seed=7),
                      "constants": {"Kp": 1.0, "Ki": 1.0}}]}
    resp = client.post("/v1/frequency-fits", json=body)
    assert resp.status_code == 200, resp.text
    result = resp.json()
    assert result["success"] is True and result["solver"]["method"] == "frequency_response"
    for n in NAMES:
        assert result["parameters"][n]["value"] == pytest.approx(TRUTH[n], rel=0.02)
    fr = result["frequency_response"]
    assert fr["stable"] is True and fr["loops"][0]["max_real_part"] < 0
    assert fr["data"][0]["omega"] == pytest.approx(omegas.tolist())
    assert len(fr["data"][0]["measured_real"]) == 20 and len(fr["data"][0]["fitted_imag"]) == 20


def test_gain_and_phase_in_db(client):
    d = frequency_data(TRUTH, 1, 1, seed=1, name="pi")
    g = np.array(d.pop("real")) + 1j * np.array(d.pop("imag"))
    d.update(gain=(20 * np.log10(np.abs(g))).tolist(), gain_unit="dB", phase_deg=np.degrees(np.angle(g)).tolist())
    resp = client.post("/v1/frequency-fits", json={"model": seed001_model(GUESS), "data": [d]})
    assert resp.status_code == 200, resp.text
    for n in NAMES:
        assert resp.json()["parameters"][n]["value"] == pytest.approx(TRUTH[n], rel=0.02)


def _body(**data_changes) -> dict:
    d = frequency_data(TRUTH, 1, 1, omega=np.array([1.0, 2.0, 3.0, 4.0, 5.0]), level=0.0, name="pi")
    d.update(data_changes)
    return {"model": seed001_model(GUESS), "data": [d]}


@pytest.mark.parametrize("changes,field,fragment", [
    ({"omega": [-1.0, 2.0, 3.0, 4.0, 5.0]}, "data[0].omega", "must be positive"),
    ({"omega": [1.0, 2.0, 2.0, 4.0, 5.0]}, "data[0].omega", "strictly increasing"),
    ({"imag": [0.1, 0.2, 0.3]}, "data[0].imag", "3 values, omega has 5"),
])
def test_bad_data_is_a_422_naming_the_field(client, changes, field, fragment):
    body = assert_problem(client.post("/v1/frequency-fits", json=_body(**changes)), 422, field, fragment)
    assert body["errors"][0]["loc"] == field


def test_sine_test_with_mismatched_lengths_is_a_422(client):
    records = sine_records(TRUTH, 1, 1, [1.0], noise=0.0, seed=0)
    records[0]["output"] = records[0]["output"][:-3]
    body = {"model": seed001_model(GUESS), "data": [{"sine_tests": records}]}
    assert_problem(client.post("/v1/frequency-fits", json=body), 422, "data[0].sine_tests[0].output",
                   "give one value per time sample")


def test_improper_transfer_function_is_a_422(client):
    body = _body()
    body["model"]["numerator"] = ["b1", "0", "b2", "0", "0", "0"]
    assert_problem(client.post("/v1/frequency-fits", json=body), 422, "model.numerator", "improper")


def test_time_domain_fit_refuses_the_frequency_method(client, example):
    example["method"] = "frequency_response"
    assert_problem(client.post("/v1/fits", json=example), 422, "/v1/frequency-fits")


def test_cli_fit_accepts_a_frequency_request(tmp_path, capsys):
    path = tmp_path / "freq.json"
    path.write_text(json.dumps({"model": seed001_model(GUESS),
                                "data": [frequency_data(TRUTH, 1, 1, seed=2, name="pi")]}))
    assert cli_main(["fit", str(path)]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["parameters"]["a3"]["value"] == pytest.approx(TRUTH["a3"], rel=0.02)
    assert result["frequency_response"]["stable"] is True


@pytest.mark.parametrize("where,value,field", [
    ("constants", {"Kp": 1.0, "Ki": 1e308}, "data[0].constants"),
    ("also_stable_with", [{"Kp": 3.0, "Ki": -1e308}], "options.also_stable_with[0]"),
])
def test_constants_that_overflow_the_loop_are_a_422_naming_them(client, where, value, field):
    """Finite but so large that the closed loop's coefficients overflow (these were 500s: the Levy
    start's SVD and the pole report's eigenvalues failed on them)."""
    body = _body()
    if where == "constants":
        body["data"][0]["constants"] = value
    else:
        body["options"] = {"also_stable_with": value}
    body = assert_problem(client.post("/v1/frequency-fits", json=body), 422, field, "overflow")
    assert body["errors"][0]["loc"] == field


def test_measured_response_near_the_float_limit_is_an_answer_not_a_500(client):
    """A measured point of -1e308 among exact ones: the Levy start is skipped (its SVD does not
    converge; this was a 500) and the relative cost bounds that point's residual by 1, so the other
    points still give the truth."""
    body = _body()
    body["data"][0]["imag"][2] = -1e308
    resp = client.post("/v1/frequency-fits", json=body)
    assert resp.status_code == 200, resp.text
    result = resp.json()
    assert result["frequency_response"]["levy_start"] is None
    for n in NAMES:
        assert result["parameters"][n]["value"] == pytest.approx(TRUTH[n], rel=1e-3)
