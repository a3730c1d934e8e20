"""Clients, not one key: each named key sees, lists and cancels only its own jobs (another's is a
404, as a job that does not exist), on SQLite and PostgreSQL; a revoked key is refused at once;
no key is ever written to a log, the metrics or an error; a store made before clients keeps its
jobs for the single GREYFIT_API_KEY."""
import json
import time
import uuid

import httpx
import pytest
from fastapi.testclient import TestClient
from sqlalchemy import create_engine, text

from greyfit.service.cli.commands import main as greyfit
from greyfit.service.http.app import create_app
from greyfit.service.http.clients import KeyStore
from greyfit.service.jobs.store import JobStore, make_engine
from tests.servers import free_port, start_server, stop_server
from tests.service.conftest import make_settings, msd_request, slow_request

LEGACY_KEY = "the-single-legacy-key-" + uuid.uuid4().hex


def bearer(key: str) -> dict:
    return {"Authorization": f"Bearer {key}"}


def old_store_with_a_job(url: str) -> str:
    """A store as a server before clients left it (no jobs.client), holding one job."""
    engine = make_engine(url)
    job_id = JobStore(engine).create_job("fit", [msd_request(0, n=21)], "before clients")
    with engine.begin() as conn:
        if engine.dialect.name == "sqlite":
            conn.execute(text("DROP INDEX ix_jobs_client"))
        conn.execute(text("ALTER TABLE jobs DROP COLUMN client"))
    engine.dispose()
    return job_id


CAPTURED: list[str] = []   # what was written on stdout and stderr (logs included), but the new keys


def cli(capsys, *args: str) -> tuple[int, str]:
    """`greyfit keys ARGS`: exit code and stdout (the rest, and what was written before, to CAPTURED)."""
    CAPTURED.append("".join(capsys.readouterr()))
    code = greyfit(["keys", *args])
    out, err = capsys.readouterr()
    CAPTURED.append(err if args[0] == "add" else out + err)
    return code, out


def test_two_clients_never_see_each_others_jobs(tmp_path, store_url, monkeypatch, capsys):
    monkeypatch.setenv("GREYFIT_DATABASE_URL", store_url)
    CAPTURED.clear()
    old_job = old_store_with_a_job(store_url)
    code, key_a = cli(capsys, "add", "team-a")
    assert code == 0 and key_a.startswith("gfk_") and len(key_a.strip()) == 47
    key_a, key_b = key_a.strip(), cli(capsys, "add", "team-b")[1].strip()
    settings = make_settings(tmp_path, database_url=store_url, api_key=LEGACY_KEY, workers=1, log_level="DEBUG")
    seen: list[str] = []   # every answer's text, searched for keys at the end
    with TestClient(create_app(settings)) as http:
        def call(method: str, path: str, key: str, **kw):
            answer = http.request(method, path, headers={**bearer(key), **kw.pop("headers", {})}, **kw)
            seen.append(answer.text + json.dumps(dict(answer.headers)))
            return answer

        body = {"requests": [msd_request(0, n=21)]}
        jobs = {k: call("POST", "/v1/jobs", k, json=body).json()["id"] for k in (key_a, key_b)}
        jobs[LEGACY_KEY] = old_job
        for key, mine in jobs.items():
            listed = call("GET", "/v1/jobs", key).json()
            assert [j["id"] for j in listed["data"]] == [mine] and listed["count"] == 1
            assert call("GET", f"/v1/jobs/{mine}", key).status_code == 200
            for other in set(jobs.values()) - {mine}:
                for method, path in [("GET", f"/v1/jobs/{other}"), ("GET", f"/v1/jobs/{other}/results"),
                                     ("GET", f"/v1/jobs/{other}/report"), ("DELETE", f"/v1/jobs/{other}")]:
                    answer = call(method, path, key)
                    assert answer.status_code == 404, (method, path, answer.text)
                    assert answer.json()["detail"] == f"no job with id '{other}'"   # as if there were none
        assert call("DELETE", f"/v1/jobs/{jobs[key_b]}", key_b).status_code == 200   # its own: cancelled

        # one Idempotency-Key sent by two clients: two jobs, each its sender's
        same = {"Idempotency-Key": "retry-1"}
        first = call("POST", "/v1/jobs", key_a, json=body, headers=same).json()["id"]
        again = call("POST", "/v1/jobs", key_a, json=body, headers=same).json()["id"]
        other = call("POST", "/v1/jobs", key_b, json=body, headers=same).json()["id"]
        assert first == again != other

        # revoked with the command line: refused at once, the other client unaffected
        assert cli(capsys, "revoke", "team-b")[0] == 0
        assert call("GET", "/v1/jobs", key_b).status_code == 401
        assert call("GET", f"/v1/jobs/{jobs[key_a]}", key_a).status_code == 200
        assert call("GET", "/v1/jobs", key_a + "x").status_code == 401
        assert call("GET", "/v1/jobs", "").status_code == 401
        metrics = call("GET", "/metrics", key_a).text
        listing = cli(capsys, "list")[1]
        assert "team-a\t" in listing and "team-b\t" in listing and "revoked" in listing
    CAPTURED.append("".join(capsys.readouterr()))
    logs = "".join(CAPTURED)
    assert "revoked" in logs and '"level"' in logs   # the command line's lines and the server's JSON logs
    for key in (key_a, key_b, LEGACY_KEY):
        for where, output in [("answers", "".join(seen)), ("metrics", metrics), ("key list", listing),
                              ("logs", logs)]:
            assert key not in output, where


def test_rate_limit_per_client_and_the_first_key_closes_an_open_server(tmp_path):
    settings = make_settings(tmp_path, workers=1, rate_limit_per_minute=3)
    with TestClient(create_app(settings)) as http:
        assert http.get("/v1/jobs").status_code == 200          # no keys: open, as before
        keys = KeyStore(http.app.state.store.engine)
        key_a, key_b = keys.add("a"), keys.add("b")
        time.sleep(1.1)   # NO_KEYS_RECHECK_SECONDS: a server that had no keys reads them again
        assert http.get("/v1/jobs").status_code == 401
        assert [http.get("/v1/jobs", headers=bearer(key_a)).status_code for _ in range(4)] == [200, 200, 200, 429]
        assert http.get("/v1/jobs", headers=bearer(key_b)).status_code == 200   # its own bucket
        keys.revoke("a")
        keys.revoke("b")
        # every key revoked: the server stays closed, it does not open again
        assert [http.get("/v1/jobs", headers=h).status_code for h in (bearer(key_b), {})] == [401, 401]
        # keys that cannot be read: 503 + Retry-After, naming neither the key nor the database's text
        http.app.state.keys = KeyStore(create_engine(f"sqlite:///{tmp_path}/no-such-folder/greyfit.db"))
        answer = http.get("/v1/jobs", headers=bearer(key_a))
        assert answer.status_code == 503 and answer.headers["Retry-After"] == "2"
        assert key_a not in answer.text and "no-such-folder" not in answer.text, answer.text


@pytest.mark.parametrize("name", ["", "a b", ".x", "x/y", "x" * 65, "é"])
def test_key_names_are_checked(tmp_path, monkeypatch, capsys, name):
    monkeypatch.setenv("GREYFIT_DATA_DIR", str(tmp_path))
    code, out = cli(capsys, "add", name)
    assert code == 2 and out == "" and "invalid key name" in CAPTURED[-1]


def test_a_real_server_writes_no_key_to_its_log(tmp_path):
    """uvicorn's own lines too (the access log, errors), which a TestClient does not run."""
    engine = make_engine(f"sqlite:///{tmp_path / 'greyfit.db'}")
    keys = KeyStore(engine)
    key_a, key_b = keys.add("a"), keys.add("b")
    port, log = free_port(), tmp_path / "server.log"
    server = start_server(tmp_path, port, workers=1, log=log, GREYFIT_API_KEY=LEGACY_KEY, GREYFIT_LOG_LEVEL="DEBUG")
    try:
        base = f"http://127.0.0.1:{port}"
        job = httpx.post(f"{base}/v1/jobs", json={"requests": [msd_request(0, n=21)]}, headers=bearer(key_a)).json()
        keys.revoke("b")
        statuses = [httpx.get(f"{base}{path}", headers=bearer(key)).status_code for path, key in [
            (f"/v1/jobs/{job['id']}", key_a), (f"/v1/jobs/{job['id']}", key_b), ("/v1/jobs", key_a[:-1]),
            (f"/v1/jobs/{job['id']}", LEGACY_KEY), ("/metrics", LEGACY_KEY)]]
        assert statuses == [200, 401, 401, 404, 200]
        metrics = httpx.get(f"{base}/metrics", headers=bearer(key_a)).text
    finally:
        stop_server(server)
        engine.dispose()
    written = log.read_text()
    assert "/v1/jobs" in written   # the access log was written
    for key in (key_a, key_b, LEGACY_KEY):
        assert key not in written and key[:-1] not in written and key not in metrics


def test_a_client_that_fills_its_own_queue_does_not_stop_another(tmp_path):
    settings = make_settings(tmp_path, workers=1, max_queued_tasks_per_client=3)
    with TestClient(create_app(settings)) as http:
        keys = KeyStore(http.app.state.store.engine)
        key_a, key_b = keys.add("a"), keys.add("b")
        time.sleep(1.1)   # NO_KEYS_RECHECK_SECONDS
        # a's slow task holds the one worker; the two behind it stay queued
        first = http.post("/v1/jobs", headers=bearer(key_a),
                          json={"requests": [slow_request()] + [msd_request(0, n=41)] * 2})
        assert first.status_code == 202, first.text
        refused = http.post("/v1/jobs", headers=bearer(key_a), json={"requests": [msd_request(1, n=41)] * 2})
        assert refused.status_code == 503 and "GREYFIT_MAX_QUEUED_TASKS_PER_CLIENT" in refused.text
        assert int(refused.headers["retry-after"]) >= 1
        too_many = http.post("/v1/jobs", headers=bearer(key_b), json={"requests": [msd_request(1, n=41)] * 4})
        assert too_many.status_code == 422 and "GREYFIT_MAX_QUEUED_TASKS_PER_CLIENT" in too_many.text
        other = http.post("/v1/jobs", headers=bearer(key_b), json={"requests": [msd_request(1, n=41)] * 2})
        assert other.status_code == 202, other.text   # b's own room is untouched by a's queue
        http.delete(f"/v1/jobs/{first.json()['id']}", headers=bearer(key_a))
