"""Strict input: a string or a boolean is not a number, a misspelt field gets "did you mean", one
location syntax in the HTTP answer and on the command line, 415 for a body not sent as JSON, the
request id in every error body."""
import copy
import json
import subprocess
import sys
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from greyfit.service.http.app import create_app
from greyfit.service.http.json_body import LARGE_BODY_BYTES
from greyfit.service.http.openapi_examples import examples as openapi_examples
from greyfit.service.task_kinds import KINDS
from tests.service.conftest import EXAMPLE, assert_problem, make_settings

ROOT = Path(__file__).resolve().parents[2]


def errors_of(resp) -> dict[str, str]:
    body = assert_problem(resp, 422)
    return {e["loc"]: e["msg"] for e in body["errors"]}


@pytest.mark.parametrize("where, value", [
    (("model", "parameters", 1, "value"), "0.3"),     # a parameter's start as a string
    (("experiments", 0, "time", 3), True),             # a boolean in a data series
    (("experiments", 0, "inputs", "u", 5), "0.5"),     # a string in a data series
    (("options", "max_iter"), "50"),                   # an integer as a string
    (("options", "max_iter"), 50.0),                   # an integer as a float
    (("options", "return_traces"), 1),                 # a number for a boolean
])
def test_a_string_or_boolean_is_not_a_number(client, example, where, value):
    body = copy.deepcopy(example)
    body.setdefault("options", {})
    target = body
    for part in where[:-1]:
        target = target[part]
    target[where[-1]] = value
    errors = errors_of(client.post("/v1/fits", json=body))
    loc = "".join(f"[{p}]" if isinstance(p, int) else (f".{p}" if i else p) for i, p in enumerate(where))
    assert list(errors) == [loc], errors
    assert "not a string" in errors[loc] or "true or false is expected" in errors[loc]


def _routes_taking_a_seed(spec: dict) -> set[str]:
    """The POST routes whose body holds a `seed` somewhere (options of a fit, a discovery or a frequency fit)."""
    schemas = spec["components"]["schemas"]

    def holds_seed(node, seen: frozenset) -> bool:
        if isinstance(node, dict):
            ref = node.get("$ref", "").rsplit("/", 1)[-1]
            if ref:
                return ref not in seen and holds_seed(schemas[ref], seen | {ref})
            return "seed" in node.get("properties", {}) or any(holds_seed(v, seen) for v in node.values())
        return isinstance(node, list) and any(holds_seed(v, seen) for v in node)

    return {path for path, ops in spec["paths"].items()
            if holds_seed(ops.get("post", {}).get("requestBody", {}), frozenset())}


@pytest.mark.parametrize("seed", [False, True, "0", 0.0])
def test_a_seed_is_an_integer_on_every_route_that_takes_options(client, seed):
    """`seed: false` was taken for the integer 0; a string or a float is not an integer either."""
    routes = _routes_taking_a_seed(client.get("/openapi.json").json())
    jobs = {k.jobs_path: k.sync_path for k in KINDS.values() if k.jobs_path}
    assert routes == {"/v1/fits", "/v1/discover", "/v1/frequency-fits", "/v1/simulate", "/v1/report", "/v1/designs",
                      *jobs}
    known = openapi_examples()

    def example(path: str) -> dict:   # a copy: build() may hand out the example itself
        return copy.deepcopy(known[path].build())

    fit = example("/v1/fits")
    fitted = client.post("/v1/fits", json=fit)
    assert fitted.status_code == 200, fitted.text
    result = fitted.json()
    for path in sorted(routes):
        if path in jobs:
            body, loc = {"requests": [example(jobs[path])]}, "requests[0].options.seed"
            request = body["requests"][0]
        elif path == "/v1/report":
            body, loc = {"result": result, "request": copy.deepcopy(fit)}, "request.options.seed"
            request = body["request"]
        else:
            body = request = example(path)
            loc = "options.seed"
        request.setdefault("options", {})["seed"] = seed
        assert list(errors_of(client.post(path, json=body))) == [loc], path


def test_integers_stay_numbers_and_the_valid_example_still_fits(client, example):
    body = copy.deepcopy(example)
    body["model"]["parameters"][1]["value"] = 1          # an integer where a float is declared
    resp = client.post("/v1/fits", json=body)
    assert resp.status_code == 200, resp.text
    assert resp.json()["success"] is True


def test_a_batch_job_is_as_strict_as_one_fit(client, example):
    body = copy.deepcopy(example)
    body["experiments"][0]["time"][2] = "0.1"
    errors = errors_of(client.post("/v1/jobs", json={"requests": [example, body]}))
    assert list(errors) == ["requests[1].experiments[0].time[2]"], errors


@pytest.mark.parametrize("path, wrong, meant, where", [
    ((), "metod", "method", "metod"),
    (("options",), "max_itr", "max_iter", "options.max_itr"),
    (("model", "parameters", 0), "lowr", "lower", "model.parameters[0].lowr"),
])
def test_a_misspelt_field_gets_did_you_mean(client, example, path, wrong, meant, where):
    body = copy.deepcopy(example)
    body.setdefault("options", {})
    target = body
    for part in path:
        target = target[part]
    target[wrong] = 1
    errors = errors_of(client.post("/v1/fits", json=body))
    assert errors[where] == f"unknown field '{wrong}': did you mean '{meant}'?", errors


def test_an_unknown_field_far_from_any_lists_the_fields(client, example):
    body = copy.deepcopy(example)
    body["zzzz"] = 1
    msg = errors_of(client.post("/v1/fits", json=body))["zzzz"]
    assert msg.startswith("unknown field 'zzzz'; the fields here are: ") and "experiments" in msg, msg


def test_union_members_are_named_not_pydantic_labels(client, example):
    """A discriminated union (the report's `request`, a frequency fit's `model`) reports the chosen
    member's fields at the plain location; a plain union (a simulation's `fit_result`, a FitResult
    or a DiscoveryResult) names its members."""
    fit = client.post("/v1/fits", json=example).json()
    request = copy.deepcopy(example)
    request["experimentz"] = request.pop("experiments")
    errors = errors_of(client.post("/v1/report", json={"result": fit, "request": request}))
    assert errors["request.experimentz"] == "unknown field 'experimentz': did you mean 'experiments'?", errors
    assert not any("function-after" in loc or "[" in loc.split(".")[0] for loc in errors), errors
    frequency = json.loads((ROOT / "examples" / "frequency_pi_loop_request.json").read_text())
    frequency["model"]["numerater"] = frequency["model"].pop("numerator")
    errors = errors_of(client.post("/v1/frequency-fits", json=frequency))
    assert errors["model.numerater"] == "unknown field 'numerater': did you mean 'numerator'?", errors
    simulate = {"model": example["model"], "experiments": example["experiments"], "fit_result": {"success": 1}}
    errors = errors_of(client.post("/v1/simulate", json=simulate))
    assert errors["fit_result<FitResult>.status"] == "Field required", errors
    assert errors["fit_result<DiscoveryResult>.conclusion"] == "Field required", errors


def test_no_value_error_prefix(client, example):
    body = copy.deepcopy(example)
    body["method"] = "frequency_response"      # refused by a field validator's ValueError
    errors = errors_of(client.post("/v1/fits", json=body))
    assert errors["method"].startswith("frequency_response fits take a FrequencyFitRequest"), errors


@pytest.mark.parametrize("headers", [{"content-type": "text/plain"}, {},
                                     {"content-type": "application/x-www-form-urlencoded"}])
def test_a_body_not_sent_as_json_is_415(client, example, headers):
    problem = assert_problem(client.post("/v1/fits", content=json.dumps(example), headers=headers), 415,
                             "Content-Type: application/json")
    assert problem["request_id"]


@pytest.mark.parametrize("content_type", ["application/json; charset=utf-8", "application/merge-patch+json"])
def test_json_media_types_with_parameters_or_suffix_are_json(client, example, content_type):
    resp = client.post("/v1/fits", content=json.dumps(example), headers={"content-type": content_type})
    assert resp.status_code == 200, resp.text


def test_the_415_is_in_the_openapi_description(client):
    spec = client.get("/openapi.json").json()
    assert "415" in spec["paths"]["/v1/fits"]["post"]["responses"]
    assert "415" not in spec["paths"]["/v1/jobs/{job_id}"]["get"]["responses"]


def test_every_error_body_carries_the_request_id_of_its_header(client, example):
    for resp in (client.get("/v1/jobs/nope"), client.post("/v1/fits", json={"model": 1}),
                 client.post("/v1/fits", content=b"{", headers={"content-type": "application/json"})):
        assert resp.status_code >= 400
        assert resp.json()["request_id"] == resp.headers["x-request-id"], resp.text
    mine = client.get("/v1/jobs/nope", headers={"x-request-id": "trace-42.a"})
    assert mine.json()["request_id"] == "trace-42.a" == mine.headers["x-request-id"]
    odd = client.get("/v1/jobs/nope", headers={"x-request-id": "has space"})   # not a plain token: replaced
    assert odd.json()["request_id"] != "has space"


def test_a_large_body_is_as_strict(tmp_path, example):
    """Above LARGE_BODY_BYTES the body is parsed off the event loop (here in a thread): same answer."""
    n = 60_000
    body = copy.deepcopy(example)
    record = body["experiments"][0]
    record["time"] = [i * 0.001 for i in range(n)]
    record["inputs"] = {"u": [0.0] * n}
    record["outputs"] = {"x": [0.0] * n}
    record["time"][1] = "0.001"
    text = json.dumps(body)
    assert len(text) > LARGE_BODY_BYTES
    with TestClient(create_app(make_settings(tmp_path, body_parser_processes=0, workers=1))) as c:
        errors = errors_of(c.post("/v1/fits", content=text, headers={"content-type": "application/json"}))
    assert list(errors) == ["experiments[0].time[1]"] and "not a string" in errors["experiments[0].time[1]"]


def run_cli(*args: str, stdin: str | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "greyfit.service.cli", *args], cwd=ROOT, input=stdin,
                          capture_output=True, text=True, timeout=120)


def test_the_cli_is_as_strict_and_says_the_same_locations(client, example):
    body = copy.deepcopy(example)
    body["model"]["parameters"][1]["value"] = "500"
    body["experiments"][0]["time"][3] = True
    body["metod"] = "single_shooting"
    http = errors_of(client.post("/v1/fits", json=body))
    cli = run_cli("fit", "-", stdin=json.dumps(body))
    assert cli.returncode == 2 and cli.stdout == ""
    lines = cli.stderr.strip().splitlines()
    assert lines[0] == "greyfit: invalid request:"
    assert lines[1:] == [f"{loc}: {msg}" for loc, msg in http.items()]
    assert "model.parameters[1].value" in http and "parameters.1.value" not in cli.stderr


def test_the_cli_suggests_options_and_commands():
    typo = run_cli("fit", str(EXAMPLE), "--prety")
    assert typo.returncode == 2 and "unrecognized arguments: --prety (did you mean '--pretty'?)" in typo.stderr
    command = run_cli("fitt", str(EXAMPLE))
    assert command.returncode == 2 and "(did you mean 'fit'?)" in command.stderr
    far = run_cli("fit", str(EXAMPLE), "--zzzzzz")
    assert far.returncode == 2 and "did you mean" not in far.stderr
