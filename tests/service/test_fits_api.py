"""Synchronous fits and every problem+json error shape, through the real HTTP stack."""
import json
import threading

import pytest

from tests.service.conftest import assert_problem


def test_sync_fit_returns_the_result(client, example):
    resp = client.post("/v1/fits", json=example)
    assert resp.status_code == 200, resp.text
    body = resp.json()
    assert body["success"] is True
    assert body["parameters"]["c"]["value"] == pytest.approx(0.8, rel=0.03)
    assert body["parameters"]["k"]["value"] == pytest.approx(5.0, rel=0.01)
    assert body["covariance"]["names"] == ["c", "k"]


def test_a_sync_fit_goes_to_an_idle_worker_from_the_web_thread_as_its_json_text(client, example):
    """The worker gets the body as sent (validated once more there, not dumped and re-validated), and
    an idle worker gets it without the dispatcher thread (unless a dispatcher round held the lock)."""
    executor = client.app.state.dispatcher.executor
    seen, submit = [], executor.submit

    def recording_submit(key, kind, request):
        seen.append((threading.current_thread().name, kind, request))
        submit(key, kind, request)

    text = json.dumps(example, indent=1)   # not how the server would write it
    executor.submit = recording_submit
    try:
        for _ in range(3):
            resp = client.post("/v1/fits", content=text, headers={"content-type": "application/json"})
            assert resp.status_code == 200, resp.text
    finally:
        del executor.submit
    assert [(kind, request) for _, kind, request in seen] == [("fit", text)] * 3
    assert any(name != "greyfit-dispatcher" for name, _, _ in seen), seen


def test_openapi_and_docs_are_served(client):
    spec = client.get("/openapi.json").json()
    assert {"/v1/fits", "/v1/jobs", "/v1/jobs/{job_id}", "/v1/jobs/{job_id}/results", "/healthz",
            "/readyz", "/metrics"} <= set(spec["paths"])
    assert client.get("/docs").status_code == 200


def test_unknown_name_is_a_422_naming_the_field(client, example):
    example["model"]["equations"]["v"] = "(u - c*v - kk*x)/m"
    body = assert_problem(client.post("/v1/fits", json=example), 422, "equations.v", "unknown name 'kk'")
    assert body["errors"][0]["loc"] == "equations.v"


def test_import_attempt_in_expression_is_refused(client, example):
    example["model"]["equations"]["v"] = "__import__('os').system('true')"
    assert_problem(client.post("/v1/fits", json=example), 422, "equations.v", "unexpected character")


def test_million_deep_parentheses_are_refused_and_server_stays_healthy(client, example):
    example["model"]["equations"]["v"] = "(" * 10 ** 6 + "v" + ")" * 10 ** 6
    body = assert_problem(client.post("/v1/fits", json=example), 422, "model.equations.v")
    assert "at most 4000 characters" in json.dumps(body)
    assert client.get("/healthz").json() == {"status": "ok"}


def test_deeply_nested_json_is_refused(client):
    deep = "[" * 100_000 + "]" * 100_000
    resp = client.post("/v1/fits", content=deep, headers={"content-type": "application/json"})
    assert_problem(resp, 400, "nested at most")
    assert client.get("/healthz").status_code == 200


def test_malformed_json(client):
    resp = client.post("/v1/fits", content=b'{"model": ', headers={"content-type": "application/json"})
    body = assert_problem(resp, 422, "malformed JSON")
    assert body["errors"][0]["loc"]


def test_wrong_types_name_the_location(client, example):
    example["experiments"][0]["time"] = "yesterday"
    example["options"]["max_iter"] = "many"
    body = assert_problem(client.post("/v1/fits", json=example), 422)
    locs = {e["loc"] for e in body["errors"]}
    assert "experiments[0].time" in locs and "options.max_iter" in locs


def test_nan_in_data_is_refused_at_the_sample(client, example):
    text = json.dumps(example)
    x = example["experiments"][0]["outputs"]["x"]
    text = text.replace(json.dumps(x), json.dumps(x[:4] + ["__NAN__"] + x[5:])).replace('"__NAN__"', "NaN")
    resp = client.post("/v1/fits", content=text, headers={"content-type": "application/json"})
    assert_problem(resp, 422, "experiments[0].outputs.x[4]", "finite number")


def test_length_mismatch_is_a_data_error(client, example):
    example["experiments"][0]["inputs"]["u"].pop()
    assert_problem(client.post("/v1/fits", json=example), 422, "experiments[0].inputs.u", "time has 201")


def test_unknown_route_and_job_are_404_problems(client):
    assert_problem(client.get("/v1/nothing"), 404)
    assert_problem(client.get("/v1/jobs/not-a-job"), 404, "no job with id")


def test_healthy_after_all_the_bad_input(client):
    assert client.get("/healthz").json() == {"status": "ok"}
    assert client.get("/readyz").json()["status"] == "ready"
    metrics = client.get("/metrics").text
    assert 'greyfit_http_requests_total{method="POST",route="/v1/fits",status="422"}' in metrics
    assert 'greyfit_fits_total{kind="fit",status="succeeded"}' in metrics
    assert "greyfit_queue_depth 0" in metrics


def test_options_the_request_leaves_out_are_chosen_by_the_fit_as_in_the_library(client):
    """Defect: requests were passed on with every default written out, so a service fit took
    `substeps: 1` as the user's choice and never chose its substeps or refitted a smooth input
    read as ramps (the library did). A request model is sent as what was set in it."""
    from greyfit.schemas.fit import FitRequest
    from greyfit.solvers.fit import fit_model
    from tests.servers import msd_request
    from tests.service.conftest import wait_for_job

    body = msd_request(4)
    body.get("options", {}).pop("substeps", None)
    library = fit_model(FitRequest.model_validate(body))
    assert library.preprocessing.substeps is not None and library.preprocessing.input_refinement
    sent = json.loads(FitRequest.model_validate(body).model_dump_json(exclude_unset=True))
    assert "substeps" not in sent.get("options", {})
    over_http = client.post("/v1/fits", json=body).json()
    job = wait_for_job(client, client.post("/v1/jobs", json={"requests": [body]}).json()["id"])
    result = client.get(f"/v1/jobs/{job['id']}/results").json()["results"][0]["result"]
    for got in (over_http, result):
        assert got["preprocessing"]["substeps"] == library.preprocessing.substeps
        assert got["preprocessing"]["input_refinement"] == library.preprocessing.input_refinement
        assert got["parameters"]["k"]["value"] == pytest.approx(library.parameters["k"].value, rel=1e-9)
