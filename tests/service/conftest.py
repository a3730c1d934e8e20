"""TestClient on a temporary data directory, with settings overridden per test module."""
import copy
import json
import time
from pathlib import Path

import numpy as np
import pytest
from fastapi.testclient import TestClient

from service.app import create_app
from service.settings import Settings
from tests.systems import msd_experiment, msd_model, simulate_msd

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "msd_request.json"


def make_settings(tmp_path, **overrides) -> Settings:
    base = dict(data_dir=tmp_path, workers=2, lease_seconds=2.0, poll_seconds=0.02)
    base.update(overrides)
    return Settings(**base)


@pytest.fixture(scope="module")
def module_tmp(tmp_path_factory):
    return tmp_path_factory.mktemp("greyfit")


@pytest.fixture(scope="module")
def client(module_tmp):
    with TestClient(create_app(make_settings(module_tmp))) as c:
        yield c


@pytest.fixture
def example() -> dict:
    return json.loads(EXAMPLE.read_text())


def msd_request(seed: int, noise: float = 0.005, n: int = 101) -> dict:
    t = np.linspace(0, 10, n)
    return {"model": msd_model(c=0.5, k=3.0), "method": "multiple_shooting",
            "experiments": [msd_experiment(t, simulate_msd(t), noise=noise, seed=seed)]}


def slow_request() -> dict:
    """About a second of work: a 2001-sample output-error fit with several starts."""
    body = msd_request(0, n=2001)
    body["options"] = {"multistart": 4, "substeps": 4}
    return copy.deepcopy(body)


def wait_for_job(client, job_id: str, timeout: float = 120, headers=None) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        job = client.get(f"/v1/jobs/{job_id}", headers=headers).json()
        if job["status"] in ("succeeded", "failed", "cancelled"):
            return job
        time.sleep(0.1)
    raise AssertionError(f"job {job_id} did not finish in {timeout} s: {job}")


def assert_problem(resp, status: int, *fragments):
    assert resp.status_code == status, resp.text
    assert resp.headers["content-type"].startswith("application/problem+json")
    body = resp.json()
    assert body["status"] == status and body["title"] and body["type"].startswith("https://")
    text = json.dumps(body)
    for f in fragments:
        assert f in text, text
    return body
