"""Requests as an attacker or a careless client sends them: 4xx with the reason, never a 5xx."""
import json

import pytest
from fastapi.testclient import TestClient

from greyfit.service.http.app import create_app
from tests.service.conftest import assert_problem, make_settings, msd_request


@pytest.fixture(scope="module")
def keyed(module_tmp):
    with TestClient(create_app(make_settings(module_tmp / "keyed", api_key="s3cret", max_body_bytes=4096))) as c:
        yield c


def test_offset_beyond_64_bits_is_a_422(client):
    assert_problem(client.get("/v1/jobs", params={"offset": 9223372036854775808}), 422, "offset")
    assert client.get("/v1/jobs", params={"offset": 2 ** 31 - 1}).json()["data"] == []


def test_non_ascii_bearer_token_is_a_401(keyed):
    for token in ("é", "ключ", "s3cret\u00a0"):
        resp = keyed.get("/v1/jobs", headers={"Authorization": f"Bearer {token}".encode()})
        assert_problem(resp, 401, "Bearer")


@pytest.mark.parametrize("path", ["/docs", "/redoc", "/openapi.json", "/v1/jobs", "/metrics", "/nowhere"])
def test_everything_but_the_probes_needs_the_key(keyed, path):
    assert_problem(keyed.get(path), 401)
    assert keyed.get(path, headers={"Authorization": "Bearer s3cret"}).status_code in (200, 404)
    assert keyed.get("/healthz").status_code == 200 and keyed.get("/readyz").status_code == 200


def test_the_key_is_checked_before_the_body_is_read(keyed):
    malformed = keyed.post("/v1/fits", content=b'{"model": ', headers={"content-type": "application/json"})
    assert_problem(malformed, 401)
    oversized = keyed.post("/v1/fits", content=b"[" + b"0," * 50_000 + b"0]",
                           headers={"content-type": "application/json"})
    assert_problem(oversized, 401)      # not 413: nothing of an unauthenticated body is looked at


def test_duplicate_keys_are_refused(client):
    body = json.dumps(msd_request(0))
    doubled = body.replace('"method": "multiple_shooting"', '"method": "multiple_shooting", "method": "equation_error"')
    assert doubled != body
    problem = assert_problem(client.post("/v1/fits", content=doubled, headers={"content-type": "application/json"}),
                             422, "duplicate key 'method'")
    assert problem["errors"][0]["loc"] == "body"


def test_malformed_json_says_line_and_column_not_a_list_index(client):
    resp = client.post("/v1/fits", content=b'{\n  "model": ,\n}', headers={"content-type": "application/json"})
    problem = assert_problem(resp, 422, "malformed JSON", "line 2 column 12")
    assert problem["errors"][0]["loc"] == "body"


@pytest.mark.parametrize("options, where", [
    ({"output_weights": {"x": -1.0}}, "options.output_weights"),
    ({"output_weights": {"x": 0.0}}, "options.output_weights"),
    ({"derivative_window": 12}, "options.derivative_window"),
    ({"derivative_window": 5, "derivative_order": 5}, "derivative_order 5 must be below"),
    ({"derivative_window": 999}, "longer than experiments[0] (101 samples)"),
])
def test_bad_options_are_named(client, options, where):
    body = msd_request(0)
    body["options"] = options
    assert_problem(client.post("/v1/fits", json=body), 422, where)


@pytest.mark.parametrize("number", ["١", "²", "𝟙", "٣.٥"])
def test_non_ascii_digits_are_not_numbers_in_expressions(client, number):
    body = msd_request(0)
    body["model"]["equations"]["v"] = f"(u - c*v - k*x)/m + {number}*0"
    assert_problem(client.post("/v1/fits", json=body), 422, "equations.v", "unexpected character")


def test_rate_limit_answers_429_with_retry_after(tmp_path):
    with TestClient(create_app(make_settings(tmp_path, api_key="k", rate_limit_per_minute=3))) as c:
        auth = {"Authorization": "Bearer k"}
        codes = [c.get("/v1/jobs", headers=auth).status_code for _ in range(5)]
        assert codes[:3] == [200, 200, 200] and codes[3:] == [429, 429]
        resp = c.get("/v1/jobs", headers=auth)
        assert_problem(resp, 429, "GREYFIT_RATE_LIMIT_PER_MINUTE")
        assert int(resp.headers["retry-after"]) >= 1
        assert c.get("/healthz").status_code == 200       # probes are never limited


def test_bodies_beyond_the_in_flight_budget_wait_outside_with_503(tmp_path):
    """The budget counts bytes of bodies being received; one that does not fit is refused unread."""
    settings = make_settings(tmp_path, max_body_bytes=1 << 20, max_inflight_body_bytes=1 << 20)
    with TestClient(create_app(settings)) as c:
        budget = c.app.middleware_stack
        while not hasattr(budget, "inflight"):   # the BodyBudget layer of the ASGI stack
            budget = budget.app
        budget.inflight = (1 << 20) - 1000       # as if another client's large body were arriving
        resp = c.post("/v1/fits", json=msd_request(0, n=41))
        assert_problem(resp, 503, "GREYFIT_MAX_INFLIGHT_BODY_BYTES")
        assert resp.headers["retry-after"] == str(settings.retry_after_seconds)
        budget.inflight = 0
        assert c.post("/v1/fits", json=msd_request(0, n=41)).status_code == 200
        assert budget.inflight == 0              # every reservation is given back


def test_synchronous_queue_is_bounded_with_503(tmp_path):
    with TestClient(create_app(make_settings(tmp_path, workers=1, max_sync_queue=2))) as c:
        dispatcher = c.app.state.dispatcher
        slow = msd_request(0, n=2001)
        slow["options"] = {"multistart": 30, "substeps": 4}
        futures = [dispatcher.submit_sync("fit", slow) for _ in range(3)]   # one runs, two wait
        try:
            resp = c.post("/v1/fits", json=msd_request(1, n=41))
            assert_problem(resp, 503, "GREYFIT_MAX_SYNC_QUEUE", "/v1/jobs")
            assert resp.headers["retry-after"]
        finally:
            for f in futures:
                dispatcher.cancel_sync(f)
        assert c.post("/v1/fits", json=msd_request(1, n=41)).status_code == 200


def test_a_task_that_fails_unexpectedly_is_a_500_with_the_logged_request_id(tmp_path, caplog):
    """A bug inside a worker's task (here: a task kind no worker knows) is answered like any other
    bug: problem+json `internal-error` with the request id the server logged its trace under, and
    not the exception's text."""
    from fastapi import Request

    from greyfit.service.http.routes.sync import run_sync

    app = create_app(make_settings(tmp_path))

    async def worker_bug(request: Request):
        return await run_sync(request, "no-such-task", {})

    app.add_api_route("/worker-bug", worker_bug, methods=["POST"])
    with TestClient(app, raise_server_exceptions=False) as c:
        resp = c.post("/worker-bug")
    body = assert_problem(resp, 500)
    assert body["type"].endswith("/internal-error") and body["request_id"] not in (None, "-")
    assert body["request_id"] in body["detail"] and "no-such-task" not in body["detail"]
    assert any(body["request_id"] in r.getMessage() for r in caplog.records)
