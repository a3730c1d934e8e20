"""Online estimators and time-varying parameters through POST /v1/fits and `greyfit fit`."""
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.online_systems import rl_experiment, rl_model, simulate_rl
from tests.service.conftest import assert_problem

ROOT = Path(__file__).resolve().parents[2]


def rls_body(duration=1.0):
    t, u, i = simulate_rl(duration, r_of_t=lambda tt: np.where(tt < 0.5, 2.0, 3.0))
    return {"model": rl_model(), "experiments": [rl_experiment(t, u, i)], "method": "recursive_least_squares",
            "options": {"rls": {"forgetting": 0.98, "trajectory_every": 5}}}


def test_rls_over_http_returns_the_trajectory(client):
    resp = client.post("/v1/fits", json=rls_body())
    assert resp.status_code == 200, resp.text
    body = resp.json()
    assert body["solver"]["method"] == "recursive_least_squares"
    assert body["parameters"]["R"]["value"] == pytest.approx(3.0, rel=0.01)
    traj = body["trajectory"]
    times = np.array(traj["time"])
    r_hat = np.array(traj["values"]["R"])
    assert r_hat[np.searchsorted(times, 0.45)] == pytest.approx(2.0, rel=0.01)
    assert traj["excitation"]["persistently_exciting"] is True
    assert len(traj["upper"]["R"]) == times.size


def test_time_varying_over_http_and_bad_options_are_422(client):
    t, u, i = simulate_rl(1.0, r_of_t=lambda tt: 2.0 + tt)
    model = rl_model(R=2.5, L=0.6)
    model["parameters"][0]["time_varying"] = {"kind": "piecewise_linear", "segments": 2}
    resp = client.post("/v1/fits", json={"model": model, "experiments": [rl_experiment(t, u, i)],
                                         "method": "equation_error"})
    assert resp.status_code == 200, resp.text
    assert resp.json()["trajectory"]["values"]["R"][-1] == pytest.approx(3.0, rel=0.01)
    body = rls_body(0.2)
    body["options"]["rls"]["forgetting"] = 1.5
    assert_problem(client.post("/v1/fits", json=body), 422, "options.rls.forgetting")
    body = rls_body(0.2)
    body["method"] = "multiple_shooting"
    body["options"] = {"prefilter": {"cutoff_hz": 5}}
    assert_problem(client.post("/v1/fits", json=body), 422, "options.prefilter")


def test_rls_through_the_cli(tmp_path):
    path = tmp_path / "rls.json"
    path.write_text(json.dumps(rls_body()))
    proc = subprocess.run([sys.executable, "-m", "greyfit.service.cli", "fit", str(path)], cwd=ROOT,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout)
    assert result["parameters"]["L"]["value"] == pytest.approx(0.5, rel=0.01)
    assert result["trajectory"]["estimator"].startswith("recursive_least_squares")
