"""Ids, labels and indices that no job can have are refused with a 4xx naming them, on both job
stores, before the database sees them (PostgreSQL cannot store a NUL byte and raised DataError;
an index past its INTEGER range did too)."""
import pytest
from fastapi.testclient import TestClient

from greyfit.service.http.app import create_app
from tests.service.conftest import make_settings, msd_request, wait_for_job


@pytest.fixture
def app_client(store_url, tmp_path):
    with TestClient(create_app(make_settings(tmp_path, database_url=store_url)), raise_server_exceptions=False) as c:
        yield c


@pytest.mark.parametrize("path", ["/v1/jobs/{id}", "/v1/jobs/{id}/results", "/v1/jobs/{id}/report"])
@pytest.mark.parametrize("bad", ["a%00b", "x" * 37, "a%20b"])
def test_a_job_id_that_cannot_exist_is_a_422(app_client, path, bad):
    r = app_client.get(path.replace("{id}", bad))
    assert r.status_code in (404, 422), r.text       # 404: a path the router cannot match at all
    assert r.status_code != 500
    if r.status_code == 422:
        assert "job_id" in r.text


def test_cancelling_a_job_id_with_a_nul_byte_is_a_422(app_client):
    r = app_client.delete("/v1/jobs/a%00b")
    assert r.status_code == 422 and "job_id" in r.text


@pytest.mark.parametrize("label", ["with\x00nul", "line\nbreak"])
def test_a_label_with_control_characters_is_a_422(app_client, label):
    r = app_client.post("/v1/jobs", json={"requests": [msd_request(0)], "label": label})
    assert r.status_code == 422, r.text
    assert "label" in r.text


@pytest.mark.parametrize("index", [2 ** 31, 2 ** 63, 10 ** 30])
def test_a_report_index_past_any_task_is_a_422(app_client, index):
    job = app_client.post("/v1/jobs", json={"requests": [msd_request(0)]}).json()
    wait_for_job(app_client, job["id"])
    r = app_client.get(f"/v1/jobs/{job['id']}/report", params={"index": index})
    assert r.status_code == 422, r.text
    assert "index" in r.text


def test_readiness_names_the_component_not_the_path(tmp_path):
    settings = make_settings(tmp_path)
    with TestClient(create_app(settings), raise_server_exceptions=False) as c:
        assert c.get("/readyz").status_code == 200
        db = tmp_path / "greyfit.db"
        db.rename(tmp_path / "moved.db")    # the file the server writes to is gone
        r = c.get("/readyz")
        assert r.status_code == 503 and "Retry-After" in r.headers
        assert str(tmp_path) not in r.text and "job store" in r.json()["detail"]


def test_simulating_with_parameters_near_the_float_limit_is_a_422(client):
    """The simulation overflows: the initial state cannot be estimated, and the answer says so (was a 500)."""
    body = msd_request(0)
    r = client.post("/v1/simulate", json={"model": body["model"], "experiments": body["experiments"],
                                          "parameters": {"c": 1e308, "k": 1e308}})
    assert r.status_code == 422, r.text
    assert "initial state" in r.json()["detail"] or "initial_state" in r.text
