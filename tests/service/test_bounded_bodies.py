"""A request's cost is bounded before it is paid (issue 41, item 1): a body's shape (list lengths,
key counts, unknown fields) is walked before it is validated, validation stops at the first invalid
request of a job, and an answer lists a bounded number of errors with a count of the rest.

On the code before, 250 000 empty requests were validated one by one (a 422 of 500 000 errors);
an unknown field holding an object of 10^6 keys was parsed into Python twice. How long these take
and what they cost the web process is measured by bench/bench_bounds.py, not asserted here."""
import json

import pytest
from fastapi.testclient import TestClient

from greyfit.schemas.fit import FitRequest, JobCreate
from greyfit.service.http.app import create_app
from greyfit.service.http.json_parsing import MAX_ERRORS
from greyfit.service.http.json_shape import MAX_KEYS, ListLimits, ShapeError, check_shape
from tests.service.conftest import assert_problem, make_settings

JSON = {"content-type": "application/json"}


@pytest.fixture(scope="module")
def client(module_tmp):
    with TestClient(create_app(make_settings(module_tmp, workers=1))) as c:
        yield c


def empty_requests(n: int) -> bytes:
    return b'{"requests":[' + b",".join([b"{}"] * n) + b"]}"


def test_250000_empty_requests_are_refused_by_their_number(client):
    resp = client.post("/v1/jobs", content=empty_requests(250_000), headers=JSON)
    body = assert_problem(resp, 422, "requests", "the limit is 1000", "GREYFIT_MAX_BATCH_REQUESTS")
    assert body["type"].endswith("limit-exceeded")
    assert body["errors"] == [{"loc": "requests", "msg": body["errors"][0]["msg"]}]
    assert client.get("/healthz").status_code == 200


def test_a_job_is_validated_up_to_its_first_invalid_request(client, example):
    requests = [example] * 3 + [{}] * 997          # within the limit: the first invalid one is reported
    resp = client.post("/v1/jobs", content=json.dumps({"requests": requests}), headers=JSON)
    body = assert_problem(resp, 422, "requests[3].model", "requests[3].experiments")
    assert len(body["errors"]) == 3                # two errors of requests[3], and the count of the rest
    assert body["errors"][-1]["msg"].startswith("the 996 requests after requests[3] were not checked")


def test_the_errors_listed_are_capped_and_the_rest_counted(client, example):
    example["experiments"] = [{"time": "a", "outputs": "b"}] * 40   # two wrong types in each: 80 errors
    resp = client.post("/v1/fits", content=json.dumps(example), headers=JSON)
    body = assert_problem(resp, 422, "experiments[0].time")
    assert len(body["errors"]) == MAX_ERRORS + 1
    assert body["errors"][-1] == {"loc": "body", "msg": f"{80 - MAX_ERRORS} more errors not listed: fix these "
                                  "and send the body again"}


@pytest.mark.parametrize("path", ["/v1/fits", "/v1/jobs"])
@pytest.mark.parametrize("junk", ["[" + ",".join(["0"] * 10**6) + "]",
                                  "{" + ",".join(f'"{i}":0' for i in range(10**6)) + "}"])
def test_an_unknown_field_is_refused_by_its_name(client, example, path, junk):
    text = json.dumps(example if path == "/v1/fits" else {"requests": [example]})
    resp = client.post(path, content='{"junk":' + junk + "," + text[1:], headers=JSON)
    assert_problem(resp, 422, "unknown field 'junk'")


def test_an_object_of_a_million_keys_is_refused_where_any_key_is_accepted(client):
    defs = "{" + ",".join(f'"d{i}":"1"' for i in range(10**6)) + "}"
    resp = client.post("/v1/fits", content='{"model":{"definitions":' + defs + "}}", headers=JSON)
    assert_problem(resp, 422, "model.definitions", f"more than {MAX_KEYS} keys")


def test_the_shape_walk_names_unknown_fields_at_any_depth_and_passes_valid_bodies(example):
    limits = ListLimits((("requests", 2, "GREYFIT_MAX_BATCH_REQUESTS"),))
    assert check_shape(JobCreate, json.dumps({"requests": [example, example]}).encode(), limits) == 2
    assert check_shape(FitRequest, json.dumps(example).encode(), limits) is None
    escaped = json.dumps(example).replace('"model"', '"\\u006dodel"', 1)   # the same key, escaped
    assert check_shape(FitRequest, escaped.encode(), limits) is None
    example["experiments"][0]["outputz"] = {}
    with pytest.raises(ShapeError) as err:
        check_shape(FitRequest, json.dumps(example).encode(), limits)
    assert (err.value.kind, err.value.loc) == ("unknown", ("experiments", 0, "outputz"))
    with pytest.raises(ShapeError) as err:
        check_shape(JobCreate, json.dumps({"requests": [{}, {}, {}]}).encode(), limits)
    assert (err.value.kind, err.value.loc) == ("limit", ("requests",))
    assert check_shape(FitRequest, b'{"model": [1, 2', limits) is None    # malformed: the parser's to say
