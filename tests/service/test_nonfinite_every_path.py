"""One request, one answer on every path: a series with NaN, +inf or -inf in it is refused by the
library, the command line, POST /v1/fits, POST /v1/jobs and greyfit.Client, each naming the sample.

The defect: /v1/jobs and the client wrote the NaN as null (pydantic's JSON dump), so the job fitted one
sample fewer, `good`, without a word, where the other paths refused it."""
import json
import math

import pytest
from pydantic import ValidationError

import greyfit
from greyfit.client import Client, GreyfitError
from greyfit.schemas import FitRequest
from greyfit.service.cli.commands import main
from greyfit.solvers.errors import DataError
from greyfit.solvers.fit import fit_model
from tests.servers import free_port, start_server, stop_server
from tests.service.conftest import EXAMPLE, assert_problem

HOSTILE = [math.nan, math.inf, -math.inf]
INDEX = 4
WHERE = f"experiments[0].outputs.x[{INDEX}]"


def hostile_text(value: float) -> str:
    """The README's request with one output sample NaN, Infinity or -Infinity (JSON's extension tokens)."""
    body = json.loads(EXAMPLE.read_text())
    body["experiments"][0]["outputs"]["x"][INDEX] = value
    return json.dumps(body)   # allow_nan: NaN, Infinity, -Infinity


def hostile_request(value: float) -> FitRequest:
    """A validated request whose series was changed in place afterwards (no validation sees that)."""
    request = FitRequest.model_validate_json(EXAMPLE.read_text())
    request.experiments[0].outputs["x"][INDEX] = value
    return request


@pytest.mark.parametrize("value", HOSTILE)
def test_the_library_refuses_it(value):
    with pytest.raises(ValidationError) as info:
        greyfit.fit(json.loads(hostile_text(value)))
    assert [(e["type"], e["loc"]) for e in info.value.errors()] == [
        ("finite_number", ("experiments", 0, "outputs", "x", INDEX))]
    with pytest.raises(DataError, match=rf"experiments\[0\]\.outputs\.x: value at index {INDEX} is"):
        fit_model(hostile_request(value))


@pytest.mark.parametrize("value", HOSTILE)
def test_the_command_line_refuses_it(value, tmp_path, capsys):
    path = tmp_path / "hostile.json"
    path.write_text(hostile_text(value))
    assert main(["fit", str(path)]) == 2
    assert f"{WHERE}: Input should be a finite number: NaN and Infinity are refused" in capsys.readouterr().err


@pytest.mark.parametrize("value", HOSTILE)
def test_both_routes_refuse_it_with_the_same_422(client, value):
    headers = {"content-type": "application/json"}
    jobs_before = client.get("/v1/jobs").json()["count"]
    fits = assert_problem(client.post("/v1/fits", content=hostile_text(value), headers=headers), 422, WHERE)
    job_body = '{"requests": [' + hostile_text(value) + "]}"
    jobs = assert_problem(client.post("/v1/jobs", content=job_body, headers=headers), 422, f"requests[0].{WHERE}")
    assert [e["msg"] for e in fits["errors"]] == [e["msg"] for e in jobs["errors"]]
    assert client.get("/v1/jobs").json()["count"] == jobs_before   # no job of one sample fewer


def test_the_client_refuses_it_as_the_service_does(tmp_path):
    port = free_port()
    server = start_server(tmp_path, port, workers=1)
    try:
        client = Client(f"http://127.0.0.1:{port}", max_retries=0)
        for value in HOSTILE:
            for call in (lambda r: client.fit(r), lambda r: client.submit_job([r])):
                with pytest.raises(GreyfitError) as info:   # written as NaN/Infinity, never as null
                    call(hostile_request(value))
                assert info.value.status == 422 and WHERE in json.dumps(info.value.problem)
            with pytest.raises((ValidationError, GreyfitError)) as refused:   # a dict: checked before or by the server
                client.fit(json.loads(hostile_text(value)))
            assert "finite" in str(refused.value)
        assert client.list_jobs().count == 0
    finally:
        stop_server(server)
