"""A linearised ODE model through the existing frequency-fit route and the CLI (schema-driven)."""
import json

import numpy as np
import pytest
from fastapi.testclient import TestClient

from greyfit.service.cli.commands import main as cli_main
from greyfit.service.http.app import create_app
from tests.linearised_systems import (
    PENDULUM_TRUTH,
    pendulum_equilibrium,
    pendulum_model,
    pendulum_response,
    response_data,
)
from tests.service.conftest import assert_problem, make_settings

OMEGA = np.logspace(-1, 2, 41)


def _body(**operating_point) -> dict:
    model = pendulum_model({"m": 0.3, "l": 0.8, "c": 0.5})
    model["operating_point"].update(operating_point)
    return {"model": model, "data": [response_data(pendulum_response(PENDULUM_TRUTH, OMEGA), OMEGA, 0.02, 4)]}


def test_pendulum_linearised_through_http(client):
    resp = client.post("/v1/frequency-fits", json=_body())
    assert resp.status_code == 200, resp.text
    result = resp.json()
    assert result["success"] is True and result["frequency_response"]["stable"] is True
    for name, truth in PENDULUM_TRUTH.items():
        assert result["parameters"][name]["value"] == pytest.approx(truth, rel=0.02)
    point = result["frequency_response"]["operating_point"]
    assert point["th"] == pytest.approx(pendulum_equilibrium(PENDULUM_TRUTH), rel=0.01)


@pytest.mark.parametrize("operating_point,field,fragment", [
    ({"states": {"th": 0.3, "omega": 0.0}}, "model.operating_point.states.omega", "not a model state"),
    ({"states": {"th": 0.3, "om": 0.5}, "equilibrium": "given"}, "model.operating_point.states",
     "not an equilibrium"),
])
def test_bad_operating_point_is_a_422_naming_the_field(client, operating_point, field, fragment):
    assert_problem(client.post("/v1/frequency-fits", json=_body(**operating_point)), 422, field, fragment)


def test_cli_fit_accepts_a_linearised_model(tmp_path, capsys):
    path = tmp_path / "pendulum.json"
    path.write_text(json.dumps(_body()))
    assert cli_main(["fit", str(path)]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["parameters"]["m"]["value"] == pytest.approx(PENDULUM_TRUTH["m"], rel=0.02)


def test_server_limits_apply_to_the_linearised_models_equations(tmp_path):
    """The expression-length limit names the ODE equation (a linearised model has no numerator)."""
    body = _body()
    state = next(iter(body["model"]["equations"]))
    body["model"]["equations"][state] += " + 0" * 30
    with TestClient(create_app(make_settings(tmp_path, max_expression_length=100))) as small:
        assert_problem(small.post("/v1/frequency-fits", json=body), 422, f"model.equations.{state}", "limit")
