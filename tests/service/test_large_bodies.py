"""Bodies above 1 MB are parsed and validated in a parser process: the answers are those of a small body."""
import functools
import json
import os
import signal
import time

import pytest
from fastapi.testclient import TestClient

from greyfit.service.http.app import create_app
from greyfit.service.http.json_body import LARGE_BODY_BYTES
from greyfit.service.http.json_parsing import parse_and_validate
from tests.service.conftest import assert_problem, make_settings, msd_request, wait_for_job
from tests.service.test_real_server_bodies import large_fit_request

JSON = {"content-type": "application/json"}


def large_fit() -> dict:
    """A fit request of ~1.6 MB (its data are not a simulation: for bodies refused before a fit)."""
    return large_fit_request(1.6)


@functools.lru_cache
def _small_fit() -> str:
    return json.dumps(msd_request(0, n=1001))


@pytest.fixture(scope="module", params=[1, 0], ids=["parser-process", "thread"])
def large(request, module_tmp):
    settings = make_settings(module_tmp / f"p{request.param}", body_parser_processes=request.param,
                             sync_max_values=10 ** 7)
    with TestClient(create_app(settings)) as c:
        yield c


def test_a_large_valid_job_is_stored_and_run(large):
    fit = json.loads(_small_fit())
    fit["method"] = "equation_error"     # the quick method: this test is about the body
    body = {"requests": [fit] * 20, "label": "large"}
    content = json.dumps(body).encode()
    assert len(content) > LARGE_BODY_BYTES
    resp = large.post("/v1/jobs", content=content, headers=JSON)
    assert resp.status_code == 202, resp.text
    job = wait_for_job(large, resp.json()["id"], timeout=180)
    assert job["status"] == "succeeded" and job["progress"]["succeeded"] == 20, job
    for r in large.get(f"/v1/jobs/{job['id']}/results").json()["results"]:
        assert r["result"]["parameters"]["k"]["value"] == pytest.approx(5.0, rel=0.05)   # truth 5, start 3


def test_a_large_invalid_body_names_the_field(large):
    fit = large_fit()
    n = len(fit["experiments"][0]["time"])
    fit["experiments"][0]["outputs"]["x"][n - 1] = "nan please"
    resp = large.post("/v1/jobs", content=json.dumps({"requests": [fit]}), headers=JSON)
    where = f"requests[0].experiments[0].outputs.x[{n - 1}]"
    problem = assert_problem(resp, 422, where, "valid number")
    assert problem["errors"][0]["loc"] == where
    assert "nan please" not in resp.text       # the input of the error is not echoed


def test_a_large_body_with_a_duplicate_key_is_refused(large):
    text = json.dumps(large_fit())
    doubled = text.replace('"method": "multiple_shooting"', '"method": "multiple_shooting", "method": "equation_error"')
    problem = assert_problem(large.post("/v1/fits", content=doubled, headers=JSON), 422, "duplicate key 'method'")
    assert problem["errors"][0]["loc"] == "body"


def test_a_duplicate_key_deep_in_a_job_body_is_found_where_the_numbers_are():
    """Valid bodies take pydantic's JSON parser, which keeps the last of two equal keys: the
    duplicate check must still see a key twice beside arrays of numbers and inside any request."""
    from greyfit.schemas.fit import FitRequest, JobCreate
    fit = json.dumps(msd_request(0, n=41))
    x = fit.index('"x": [', fit.index('"outputs"'))
    doubled = fit[:x] + '"x": [1.0, 2e-3, -3.5], ' + fit[x:]             # outputs.x twice
    body = '{"label": "[1, 2] \\"[3]\\"", "requests": [' + ", ".join([fit] * 3 + [doubled]) + "]}"
    status, (message, _) = parse_and_validate(JobCreate, body.encode())
    assert status == "json_invalid" and "duplicate key 'x'" in message
    status, (job, texts) = parse_and_validate(JobCreate, body.replace(doubled, fit).encode())
    assert status == "ok" and job.label == '[1, 2] "[3]"' and len(texts) == 4
    assert texts[0] == FitRequest.model_validate(msd_request(0, n=41)).model_dump_json(exclude_unset=True)


def test_large_malformed_json_says_line_and_column(large):
    text = json.dumps(large_fit()) + "\n ,"
    line = text.count("\n", 0, len(text) - 1) + 1
    assert_problem(large.post("/v1/fits", content=text, headers=JSON), 422, "malformed JSON",
                   f"line {line} column 2")


def test_a_large_body_that_is_not_utf8_is_a_400(large):
    content = json.dumps(large_fit()).encode()[:-1] + b'\xff\xfe}'
    assert_problem(large.post("/v1/fits", content=content, headers=JSON), 400, "UTF-8")


def test_a_large_body_nested_too_deeply_is_refused(large):
    content = b'{"label": "' + b"x" * LARGE_BODY_BYTES + b'", "requests": ' + b"[" * 100_000 + b"]" * 100_000 + b"}"
    resp = large.post("/v1/jobs", content=content, headers=JSON)
    assert_problem(resp, 400, "nested")


def test_a_lost_parser_process_is_a_503_and_the_next_body_is_parsed(tmp_path):
    with TestClient(create_app(make_settings(tmp_path))) as c:
        bad = large_fit()
        bad["method"] = "no such method"
        content = json.dumps(bad)
        assert_problem(c.post("/v1/fits", content=content, headers=JSON), 422, "method")
        pool = c.app.state.body_parser._pool
        for pid in list(pool._processes):           # as the out-of-memory killer would
            os.kill(pid, signal.SIGKILL)
        time.sleep(0.5)
        resp = c.post("/v1/fits", content=content, headers=JSON)
        assert_problem(resp, 503, "retry")
        assert resp.headers["retry-after"] == "2"
        assert_problem(c.post("/v1/fits", content=content, headers=JSON), 422, "method")
