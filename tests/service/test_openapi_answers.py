"""Every answer matches the OpenAPI description: a walk over the server's own description.

- each path answers a method it does not serve with 405 and an `Allow` naming every method it does
  (Starlette named only those of the first route whose path matched: `DELETE /v1/jobs` said
  `Allow: POST`, although `GET /v1/jobs` exists);
- each integer query parameter takes integers only as written in digits (pydantic's lax mode took
  "1.0", " 1", "+1" and "1_0");
- with the job store out of reach, each operation that needs it answers 503 with `Retry-After`, a
  status its description lists; a 503 made anywhere else gets `Retry-After` too;
- the job report's 409 (a task without a result) is answered in that case and described.
"""
import uuid

import pytest
from fastapi import FastAPI, HTTPException
from fastapi.testclient import TestClient
from sqlalchemy import create_engine

from greyfit.service.http.app import CountRequests, create_app
from greyfit.service.http.openapi import SYNC_PATHS
from greyfit.service.http.routes.files import FILE_KINDS
from greyfit.service.metrics import Metrics
from greyfit.service.task_kinds import KINDS
from tests.servers import free_port
from tests.service.conftest import make_settings, msd_request, wait_for_job

METHODS = {"GET", "POST", "PUT", "PATCH", "DELETE"}
NOT_INTEGERS = ["1.0", " 1", "1 ", "+1", "1_0", "1e1", "\u0663", "0x1", "true"]
# the synchronous routes answer from a worker without the job store (the job report reads it);
# /metrics answers without the store's gauges (the process's and the counters stay scrapable)
# (POST /v1/fits/files, /v1/discover/files: synchronous too, from a multipart form; the store is not asked)
FILE_PATHS = {f"{KINDS[kind].sync_path}/files" for kind in FILE_KINDS}
NO_STORE = (set(SYNC_PATHS) - {"/v1/jobs/{job_id}/report"}) | {"/healthz", "/metrics"} | FILE_PATHS


@pytest.fixture(scope="module")
def served(module_tmp):
    with TestClient(create_app(make_settings(module_tmp, workers=1))) as c:
        yield c, c.get("/openapi.json").json()


def _concrete(path: str) -> str:
    return path.replace("{job_id}", str(uuid.uuid4()))


def _operations(spec: dict):
    for path, ops in spec["paths"].items():
        for method, op in ops.items():
            yield path, method.upper(), op


def _types(schema: dict) -> set:
    return {schema.get("type")} | {s.get("type") for s in schema.get("anyOf", [])}


def test_a_method_a_path_does_not_serve_gets_405_and_allow_names_every_method_it_serves(served):
    c, spec = served
    checked = 0
    for path, ops in spec["paths"].items():
        documented = {m.upper() for m in ops}
        for method in sorted(METHODS - documented):
            resp = c.request(method, _concrete(path))
            assert resp.status_code == 405, (method, path, resp.text)
            assert set(resp.headers["allow"].split(", ")) == documented, (method, path, resp.headers["allow"])
            checked += 1
    assert checked >= 4 * len(spec["paths"]) - 4   # (only two paths serve two methods)


def test_every_integer_query_parameter_takes_integers_written_in_digits_only(served):
    c, spec = served
    params = [(path, method, p["name"]) for path, method, op in _operations(spec) for p in op.get("parameters", [])
              if p["in"] == "query" and "integer" in _types(p["schema"])]
    assert {name for _, _, name in params} == {"offset", "limit", "task_offset", "task_limit", "index"}
    for path, method, name in params:
        url = _concrete(path)
        assert c.request(method, url, params={name: "1"}).status_code != 422, (path, name)
        for value in NOT_INTEGERS:
            resp = c.request(method, url, params={name: value})
            assert resp.status_code == 422, (path, name, value, resp.status_code)
            assert [e["loc"] for e in resp.json()["errors"]] == [f"query.{name}"], resp.json()


def _body(path: str):
    """A valid body for a POST operation: its task kind's example, or a job of it."""
    for kind in KINDS.values():
        if path == kind.jobs_path and kind.job_example is not None:
            return kind.job_example.build()
        if kind.example is not None and path in (kind.sync_path, kind.jobs_path):
            body = kind.example.build()
            return body if path == kind.sync_path else {"requests": [body]}
    raise LookupError(f"POST {path}: its task kind has no `example` (service/task_kinds.py)")


def test_with_the_job_store_out_of_reach_every_operation_needing_it_answers_503_with_retry_after(tmp_path):
    app = create_app(make_settings(tmp_path, workers=1))
    with TestClient(app) as c:
        spec = c.get("/openapi.json").json()
        # a database nobody listens for: each query fails as it would with PostgreSQL down
        store, engine = app.state.store, app.state.store.engine
        store.engine = create_engine(f"postgresql+psycopg://greyfit@127.0.0.1:{free_port()}/greyfit",
                                     connect_args={"connect_timeout": 2})
        seen = {}
        try:
            for path, method, op in _operations(spec):
                if path in NO_STORE:
                    continue
                resp = c.request(method, _concrete(path), json=_body(path) if method == "POST" else None)
                seen[(method, path)] = resp.status_code
                assert resp.status_code == 503, (method, path, resp.text)
                assert str(resp.status_code) in op["responses"], (method, path)
                assert int(resp.headers["retry-after"]) >= 1, (method, path)
                assert "Retry-After" in op["responses"]["503"]["headers"]
            metrics = c.get("/metrics")   # still scraped, the store's errors counted
            assert metrics.status_code == 200 and "greyfit_queue_depth" not in metrics.text
            assert 'greyfit_store_errors_total{where="http"} ' in metrics.text
        finally:
            store.engine = engine   # the shutdown hands its tasks back through the store
        assert len(seen) >= 8, seen


def test_readiness_with_its_dispatcher_stopped_answers_503_with_retry_after(tmp_path):
    app = create_app(make_settings(tmp_path, workers=1))
    with TestClient(app) as c:
        assert c.get("/readyz").status_code == 200
        app.state.dispatcher.stop()
        resp = c.get("/readyz")
        assert resp.status_code == 503 and "dispatcher" in resp.json()["detail"]
        assert int(resp.headers["retry-after"]) >= 1


def test_a_503_made_without_retry_after_gets_one_on_its_way_out():
    inner = FastAPI()

    @inner.get("/busy")
    def busy():
        raise HTTPException(503, "busy")

    @inner.get("/told")
    def told():
        raise HTTPException(503, "busy", headers={"Retry-After": "9"})

    with TestClient(CountRequests(inner, Metrics(), retry_after=7)) as c:
        assert c.get("/busy").headers["retry-after"] == "7"
        assert c.get("/told").headers.get_list("retry-after") == ["9"]   # the route's own, not a second


def test_the_job_report_of_a_task_without_a_result_is_the_409_its_description_lists(served):
    c, spec = served
    described = spec["paths"]["/v1/jobs/{job_id}/report"]["get"]["responses"]
    assert "409" in described and "failed" in described["409"]["description"]   # the case below
    assert described["409"]["content"]["application/problem+json"]["schema"] == {"$ref": "#/components/schemas/Problem"}
    failing = msd_request(0, n=41)
    failing["model"]["equations"]["v"] = "(u - c*v - kk*x)/m"      # fails in the worker: ModelDefinitionError
    job = c.post("/v1/jobs", json={"requests": [failing]}).json()
    assert wait_for_job(c, job["id"])["tasks"][0]["status"] == "failed"
    resp = c.get(f"/v1/jobs/{job['id']}/report", params={"index": 0})
    assert resp.status_code == 409, resp.text
    assert resp.headers["content-type"].startswith("application/problem+json")
    assert "failed" in resp.json()["detail"] and "result" in resp.json()["detail"]
