"""POST /v1/simulate, /v1/report, GET /v1/jobs/{id}/report and fits with validation, through the app."""
import base64
import re

import numpy as np

from tests.service.conftest import assert_problem, msd_request, wait_for_job
from tests.systems import msd_experiment, simulate_msd


def test_simulate_from_a_previous_fit_result_reproduces_its_traces(client):
    body = msd_request(1)
    body["options"] = {"return_traces": True}
    fit = client.post("/v1/fits", json=body).json()
    exp = dict(body["experiments"][0])
    resp = client.post("/v1/simulate", json={"model": body["model"], "fit_result": fit,
                                              "experiments": [exp], "horizon": 3})
    assert resp.status_code == 200, resp.text
    sim = resp.json()
    got = sim["experiments"][0]
    assert got["initial_state_source"] == "provided" and got["horizon"] == 3
    for out in ("x", "v"):
        a, b = np.array(got["outputs"][out]), np.array(fit["traces"][0]["simulated"][out])
        assert np.max(np.abs(a - b)) <= 1e-9 * np.max(np.abs(b))
    assert sim["validation"]["fit_percent"]["x"] == fit["metrics"]["fit_percent"]["x"] or \
        abs(sim["validation"]["fit_percent"]["x"] - fit["metrics"]["fit_percent"]["x"]) < 1e-6
    # without outputs: a pure simulation needs the initial state
    exp.pop("outputs")
    assert_problem(client.post("/v1/simulate", json={"model": body["model"], "experiments": [exp]}),
                   422, "experiments[0].initial_state", "initial state")
    exp["initial_state"] = {"x": 0.1, "v": 0.0}
    ok = client.post("/v1/simulate", json={"model": body["model"], "parameters": {"c": 0.8, "k": 5.0},
                                            "experiments": [exp]}).json()
    t = np.array(exp["time"])
    assert np.max(np.abs(np.array(ok["experiments"][0]["states"]["x"]) - simulate_msd(t)[0])) < 1e-3
    assert ok["validation"] is None
    assert_problem(client.post("/v1/simulate", json={"model": body["model"], "parameters": {"q": 1.0},
                                                      "experiments": [exp]}), 422, "parameters.q")


def test_fit_with_every_parameter_fixed_and_a_validation_record(client):
    body = msd_request(2)
    for p in body["model"]["parameters"]:
        p["fixed"] = True
    t = np.linspace(0, 20, 201)     # the validation record continues the estimation record at t = 10
    body["validation"] = [msd_experiment(t[100:], simulate_msd(t)[:, 100:], noise=0.005, name="later")]
    resp = client.post("/v1/fits", json=body)
    assert resp.status_code == 200, resp.text
    res = resp.json()
    assert res["success"] and res["covariance"] is None and res["solver"]["return_status"] == "Simulation"
    assert res["validation"]["experiments"][0]["initial_state_source"] == "contiguous"
    assert res["validation"]["rmse"]["x"] > 5 * 0.005       # msd_request's guesses are not the truth


def test_report_page_for_a_result_and_for_a_job(client):
    body = msd_request(3)
    body["validation"] = [msd_experiment(np.linspace(0, 10, 101), simulate_msd(np.linspace(0, 10, 101)),
                                         noise=0.005, seed=9, name="val")]
    fit = client.post("/v1/fits", json=body).json()
    resp = client.post("/v1/report", json={"result": fit, "request": body})
    assert resp.status_code == 200, resp.text
    assert resp.headers["content-type"].startswith("text/html")
    page = resp.text
    for name in ("compare_estimation", "compare_validation", "residuals", "parameters", "correlation"):
        assert f'id="fig-{name}"' in page
    job = client.post("/v1/jobs", json={"requests": [body]}).json()
    wait_for_job(client, job["id"])
    resp = client.get(f"/v1/jobs/{job['id']}/report")
    assert resp.status_code == 200 and 'id="fig-compare_validation"' in resp.text
    assert client.get(f"/v1/jobs/{job['id']}/report?index=5").status_code == 404


def png_size(page: str, figure: str) -> tuple[int, int]:
    """(width, height) in pixels of a figure embedded in a report page, from its PNG header."""
    encoded = re.search(rf'id="fig-{figure}".*?base64,([^"]+)"', page, re.S).group(1)
    header = base64.b64decode(encoded[:44])
    return int.from_bytes(header[16:20], "big"), int.from_bytes(header[20:24], "big")


def test_report_of_a_result_with_hundreds_of_parameters_stays_a_readable_page(client):
    """300 free estimates and 20 outputs: the estimates figure shows the first 40 and says so, the
    correlation matrix is drawn whole without names, the residual figure the first 6 outputs; no
    figure grows with the count (one did: 15 000 px tall, past a worker's CPU limit)."""
    body = msd_request(3)
    body["options"] = {"return_traces": True}   # the page is drawn from the result alone
    fit = client.post("/v1/fits", json=body).json()
    small = client.post("/v1/report", json={"result": fit}).text
    one = fit["parameters"]["c"]
    fit["parameters"] = {f"c{i}": {**one, "value": one["value"] * (1 + i / 300),
                                   "ci95": [v * (1 + i / 300) for v in one["ci95"]]} for i in range(300)}
    fit["parameters"]["c0"]["ci95"] = [1.1 * one["value"], 1.2 * one["value"]]   # not made by greyfit: drawn too
    names = list(fit["parameters"])
    fit["correlation"] = {"names": names, "matrix": np.eye(300).tolist()}
    analysis = fit["residual_analysis"][0]
    fit["residual_analysis"] = [{**analysis, "output": f"y{i}"} for i in range(20)]
    resp = client.post("/v1/report", json={"result": fit})
    assert resp.status_code == 200, resp.text
    page = resp.text
    assert "estimates: the first 40 of 300 free parameters are drawn" in page
    assert "correlation: 300 estimates, drawn without their names" in page
    assert "residuals: the first 6 of 20 outputs are drawn" in page
    for figure in ("parameters", "correlation", "residuals"):
        width, height = png_size(page, figure)
        assert width <= 1200 and height <= 2500, (figure, width, height)
    assert png_size(page, "compare_estimation") == png_size(small, "compare_estimation")


def test_report_request_is_held_to_the_fits_limits(tmp_path, client):
    """The request sent with a result is simulated again in the worker: the limits of a synchronous
    fit apply to it, named by field (it went to the worker unchecked)."""
    from fastapi.testclient import TestClient

    from greyfit.service.http.app import create_app
    from tests.service.conftest import make_settings

    body = msd_request(3)
    fit = client.post("/v1/fits", json=body).json()
    with TestClient(create_app(make_settings(tmp_path, max_samples_per_experiment=50))) as small:
        assert_problem(small.post("/v1/report", json={"result": fit, "request": body}), 422,
                       "request.experiments[0].time", "101 samples")
    with TestClient(create_app(make_settings(tmp_path / "b", sync_max_values=200))) as small:
        assert_problem(small.post("/v1/report", json={"result": fit, "request": body}), 413,
                       "greyfit report result.json")
        assert small.post("/v1/report", json={"result": fit}).status_code == 200
