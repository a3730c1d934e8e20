"""POST /v1/discover, discovery jobs and `greyfit discover` through their real front ends."""
import json
import subprocess
import sys
from pathlib import Path

import jsonschema_rs
import numpy as np
import pytest

from tests.service.conftest import assert_problem, wait_for_job
from tests.systems import msd_experiment, msd_model, simulate_msd

ROOT = Path(__file__).resolve().parents[2]


def duffing_body() -> dict:
    t = np.linspace(0, 20, 1001)
    states = simulate_msd(t, extra_force=lambda x, v: 20.0 * x ** 3)
    return {"model": msd_model(), "experiments": [msd_experiment(t, states, noise=0.002, seed=1)],
            "method": "multiple_shooting", "discovery": {"max_terms": 2}}


def test_discover_endpoint_finds_the_cubic_spring(client):
    resp = client.post("/v1/discover", json=duffing_body())
    assert resp.status_code == 200, resp.text
    body = resp.json()
    assert body["steps"][0]["effect"] == "cubic_stiffness"
    assert body["steps"][0]["parameters"][0]["value"] == pytest.approx(20.0, rel=0.05)
    assert body["after"]["rmse"]["x"] < 0.5 * body["before"]["rmse"]["x"]
    assert "x^3" in body["model"]["equations"]["v"]
    # as the OpenAPI describes it, also where the correlation after the refit is not defined (it
    # was NaN, sent as null where the schema said number)
    assert abs(body["steps"][0]["evidence"]["residual_correlation_after"]) < 0.1
    spec = client.get("/openapi.json").json()
    schema = jsonschema_rs.validator_for({"$ref": "#/components/schemas/DiscoveryResult",
                                          "components": spec["components"]})
    assert not [e.message for e in schema.iter_errors(body)][:3]
    body["steps"][0]["evidence"]["residual_correlation_after"] = None
    assert not [e.message for e in schema.iter_errors(body)][:3]


def test_discover_rejects_bad_options_naming_the_field(client):
    body = duffing_body()
    body["discovery"]["effects"] = ["magic"]
    assert_problem(client.post("/v1/discover", json=body), 422, "discovery.effects[0]")
    body = duffing_body()
    body["discovery"]["candidates"] = [{"equation": "v", "term": "x^^3", "parameter": "kc"}]
    assert_problem(client.post("/v1/discover", json=body), 422, "discovery.candidates[0].term")
    body["discovery"]["candidates"] = [{"equation": "w", "term": "x^3", "parameter": "kc"}]
    assert_problem(client.post("/v1/discover", json=body), 422, "discovery.candidates[0].equation")


def test_discovery_as_a_batch_job(client):
    complete = duffing_body()
    complete["experiments"] = [msd_experiment(np.linspace(0, 20, 1001), simulate_msd(np.linspace(0, 20, 1001)),
                                              noise=0.002, seed=2)]
    resp = client.post("/v1/discover/jobs", json={"requests": [duffing_body(), complete]})
    assert resp.status_code == 202
    job = wait_for_job(client, resp.json()["id"])
    assert job["kind"] == "discover" and job["status"] == "succeeded"
    results = client.get(f"/v1/jobs/{job['id']}/results").json()["results"]
    assert results[0]["result"]["steps"][0]["effect"] == "cubic_stiffness"
    assert results[1]["result"]["conclusion"].startswith("no significant missing effect")


def test_cli_discover_prints_a_report_the_json_and_its_progress(tmp_path):
    path = tmp_path / "discover.json"
    path.write_text(json.dumps(duffing_body()))
    proc = subprocess.run([sys.executable, "-m", "greyfit.service.cli", "discover", str(path), "--summary",
                           "-o", str(tmp_path / "result.json")], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    assert json.loads((tmp_path / "result.json").read_text())["steps"][0]["effect"] == "cubic_stiffness"
    assert "RMSE before" in proc.stdout and "+ cubic_stiffness in dv/dt" in proc.stdout
    # the progress lines (stderr is not a terminal here: one line per event)
    progress = [line for line in proc.stderr.splitlines() if line.startswith("greyfit discover [")]
    assert "fitting the declared model" in progress[0] and "done: added cubic_stiffness" in progress[-1]
    assert any("refitting with" in line for line in progress)
    assert any("screening the effect library (round 1)" in line for line in progress)
