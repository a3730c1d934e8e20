"""Frequency-response fits as batch jobs: through the HTTP API, across a restart, and with `greyfit batch`."""
import json
import subprocess
import sys
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from greyfit.service.http.app import create_app
from greyfit.service.jobs.store import JobStore, make_engine
from tests.frequency_systems import NAMES, TRUTH, frequency_data, seed001_model
from tests.service.conftest import assert_problem, make_settings, wait_for_job

ROOT = Path(__file__).resolve().parents[2]
GUESS = {n: 1.5 * v for n, v in TRUTH.items()}


def frequency_request(seed: int) -> dict:
    """Seed 001's closed loop with (Kp, Ki) = (1, 1), 41 frequencies, 2 % noise."""
    return {"model": seed001_model(GUESS), "data": [frequency_data(TRUTH, 1, 1, seed=seed, name="pi")]}


def improper_request() -> dict:
    body = frequency_request(0)
    body["model"]["numerator"] = ["b1", "0", "b2", "0", "0", "0"]    # degree 5 over degree 4
    return body


def assert_recovered(result: dict) -> None:
    assert result["success"] is True and result["solver"]["method"] == "frequency_response"
    for n in NAMES:
        assert result["parameters"][n]["value"] == pytest.approx(TRUTH[n], rel=0.02), n
    assert result["frequency_response"]["stable"] is True


def test_a_frequency_job_runs_each_request_and_keeps_its_results(client):
    body = {"requests": [frequency_request(1), improper_request(), frequency_request(2)], "label": "bode"}
    resp = client.post("/v1/frequency-fits/jobs", json=body)
    assert resp.status_code == 202, resp.text
    assert resp.headers["location"] == f"/v1/jobs/{resp.json()['id']}"
    assert resp.json()["kind"] == "frequency_fit"
    job = wait_for_job(client, resp.json()["id"])
    assert job["status"] == "succeeded" and job["label"] == "bode"     # a job succeeds if any task did
    assert job["progress"] == {"done": 3, "total": 3, "succeeded": 2, "failed": 1}
    error = job["tasks"][1]["error"]
    assert error["type"] == "ModelDefinitionError" and error["field"] == "model.numerator"
    assert "improper" in error["detail"]
    results = client.get(f"/v1/jobs/{job['id']}/results").json()["results"]
    assert [r["index"] for r in results] == [0, 1, 2]
    assert_recovered(results[0]["result"])
    assert_recovered(results[2]["result"])
    assert results[1]["result"] is None and results[1]["error"]["field"] == "model.numerator"
    listed = client.get("/v1/jobs").json()["data"]
    assert any(j["id"] == job["id"] and j["kind"] == "frequency_fit" for j in listed)


def test_an_invalid_frequency_job_is_refused_whole_naming_the_request(client):
    bad = frequency_request(0)
    bad["data"][0]["imag"] = "not a list"
    resp = client.post("/v1/frequency-fits/jobs", json={"requests": [frequency_request(0), bad]})
    problem = assert_problem(resp, 422, "requests[1].data[0].imag")
    assert problem["errors"][0]["loc"] == "requests[1].data[0].imag"


def test_this_servers_limits_apply_to_frequency_jobs(tmp_path):
    with TestClient(create_app(make_settings(tmp_path, max_parameters=4, max_samples_per_experiment=40))) as c:
        resp = c.post("/v1/frequency-fits/jobs", json={"requests": [frequency_request(0)]})
        assert_problem(resp, 422, "requests[0].model.parameters", "5 parameters, the limit is 4")
        resp = c.post("/v1/frequency-fits", json=frequency_request(0))
        assert_problem(resp, 422, "model.parameters")
    with TestClient(create_app(make_settings(tmp_path, max_samples_per_experiment=40))) as c:
        resp = c.post("/v1/frequency-fits/jobs", json={"requests": [frequency_request(0)]})
        assert_problem(resp, 422, "requests[0].data[0].omega", "41 samples, the limit is 40")


def test_a_frequency_job_survives_a_restart(tmp_path):
    """The server stops with tasks queued and running; the next one on the same store finishes them."""
    settings = make_settings(tmp_path, workers=1)
    with TestClient(create_app(settings)) as c:
        job_id = c.post("/v1/frequency-fits/jobs",
                        json={"requests": [frequency_request(s) for s in range(4)]}).json()["id"]
    store = JobStore(make_engine(settings.resolved_database_url()))
    unfinished = [t for t in store.get_job(job_id)["tasks"] if t["status"] != "succeeded"]
    store.engine.dispose()
    assert unfinished, "the job finished before the restart; make it longer"
    with TestClient(create_app(settings)) as c:
        job = wait_for_job(c, job_id)
        assert job["status"] == "succeeded" and job["progress"]["succeeded"] == 4, job
        assert all(t["attempts"] == 1 for t in job["tasks"])     # a graceful stop counts no attempt
        for r in c.get(f"/v1/jobs/{job_id}/results").json()["results"]:
            assert_recovered(r["result"])


@pytest.mark.slow
def test_greyfit_batch_runs_frequency_requests(tmp_path):
    requests, out = tmp_path / "requests.jsonl", tmp_path / "results.jsonl"
    bad = frequency_request(4)
    bad["data"][0]["omega"][3] = -1.0
    requests.write_text("\n".join(json.dumps(b) for b in [frequency_request(3), bad, {"model": {}}]) + "\n")
    proc = subprocess.run([sys.executable, "-m", "greyfit.service.cli", "batch", str(requests), "--out", str(out),
                           "--workers", "1", "--kind", "frequency_fit"], cwd=ROOT, capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    by_line = {r["line"]: r for r in map(json.loads, out.read_text().splitlines())}
    assert_recovered(by_line[1]["result"])
    assert by_line[2]["status"] == "failed" and by_line[2]["error"]["type"] == "DataError"
    assert by_line[2]["error"]["field"] == "data[0].omega"
    assert by_line[3]["status"] == "failed" and by_line[3]["error"]["type"] == "ValidationError"
