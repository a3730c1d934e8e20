"""POST /v1/designs through a worker: the example's design, and a bad one named (issue 44)."""
from greyfit.service.http.openapi_examples import msd_design
from tests.service.conftest import assert_problem


def test_the_example_design_answers_with_the_predicted_gain(client):
    answer = client.post("/v1/designs", json=msd_design())
    assert answer.status_code == 200, answer.text
    result = answer.json()
    assert result["criterion"] == "D" and len(result["experiment"]["time"]) == 101
    assert result["experiment"]["time"][3] == 0.3
    u = result["experiment"]["inputs"]["u"]
    assert min(u) >= -1.0 - 1e-9 and max(u) <= 1.0 + 1e-9
    for name in ("c", "k"):   # the designed input beats the one step on both parameters
        predicted = result["parameters"][name]
        assert predicted["stderr"] < predicted["stderr_baseline"]
    assert result["improvement"] > 2.0


def test_a_design_with_no_free_input_is_a_422_naming_the_field(client):
    body = {**msd_design(), "inputs": {"u": {"value": 0.5}}}
    assert_problem(client.post("/v1/designs", json=body), 422, "inputs")
