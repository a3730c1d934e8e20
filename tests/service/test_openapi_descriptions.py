"""The OpenAPI description as a client generator reads it: a description on every property, an
operationId written by hand on every operation, schemas for the probes, examples that are what the
service answers (each valid against its schema), and job timestamps in RFC 3339."""
from datetime import datetime, timedelta

import jsonschema_rs
import pytest
from fastapi.testclient import TestClient

from greyfit.schemas import FitRequest
from greyfit.service.http.app import create_app
from greyfit.service.http.openapi import OPERATION_IDS
from greyfit.service.http.openapi_examples import msd_result
from tests.service.conftest import EXAMPLE, make_settings, msd_request, wait_for_job


@pytest.fixture(scope="module")
def served(module_tmp):
    with TestClient(create_app(make_settings(module_tmp, workers=1))) as c:
        yield c, c.get("/openapi.json").json()


def undescribed(spec: dict) -> list[str]:
    return [f"{name}.{prop}" for name, schema in spec["components"]["schemas"].items()
            for prop, sub in (schema.get("properties") or {}).items() if not sub.get("description")]


def validator(spec: dict, schema: dict):
    return jsonschema_rs.validator_for({**schema, "components": spec["components"]})


def test_every_property_is_described(served):
    spec = served[1]
    count = sum(len(s.get("properties") or {}) for s in spec["components"]["schemas"].values())
    assert count > 500 and undescribed(spec) == []


def test_every_operation_has_its_hand_written_id(served):
    spec = served[1]
    ids = {(method, path): op.get("operationId") for path, ops in spec["paths"].items() for method, op in ops.items()}
    assert ids == OPERATION_IDS
    assert len(set(ids.values())) == len(ids)


def test_the_probes_answer_what_their_schemas_say(served):
    client, spec = served
    for path, name in (("/healthz", "Health"), ("/readyz", "Readiness")):
        schema = spec["paths"][path]["get"]["responses"]["200"]["content"]["application/json"]["schema"]
        assert schema == {"$ref": f"#/components/schemas/{name}"}
        answer = client.get(path)
        assert answer.status_code == 200
        assert validator(spec, schema).is_valid(answer.json()), answer.json()
    assert client.get("/readyz").json() == {"status": "ready", "executor": "local"}


def test_every_example_answer_is_valid_against_its_schema(served):
    spec, checked = served[1], 0
    for path, ops in spec["paths"].items():
        for method, op in ops.items():
            for status, answer in op["responses"].items():
                for media in (answer.get("content") or {}).values():
                    if "example" in media:
                        errors = [e.message for e in validator(spec, media["schema"]).iter_errors(media["example"])]
                        assert errors == [], (method, path, status, errors[:3])
                        checked += 1
    assert checked >= 20     # every 422, the probes, the fit, the jobs


def test_the_example_result_is_the_example_fits():
    from greyfit.solvers.fit import fit_model
    fresh = fit_model(FitRequest.model_validate_json(EXAMPLE.read_text()))
    shipped = msd_result()["parameters"]
    for name, estimate in fresh.parameters.items():
        assert shipped[name]["value"] == pytest.approx(estimate.value, rel=1e-9, abs=1e-12)
        if estimate.stderr is not None:
            assert shipped[name]["stderr"] == pytest.approx(estimate.stderr, rel=1e-6)


def test_job_times_are_rfc_3339_in_utc(served):
    client, spec = served
    job = client.post("/v1/jobs", json={"requests": [msd_request(3)]}).json()
    record = wait_for_job(client, job["id"])
    stamps = [record["created_at"], record["started_at"], record["finished_at"],
              record["tasks"][0]["started_at"], record["tasks"][0]["finished_at"]]
    times = [datetime.fromisoformat(s.replace("Z", "+00:00")) for s in stamps]
    assert all(s.endswith("Z") for s in stamps) and all(t.utcoffset() == timedelta(0) for t in times)
    assert times[0] <= times[1] <= times[2] and times[3] <= times[4]
    listed = client.get("/v1/jobs").json()["data"][0]
    assert listed["created_at"] == record["created_at"]
    schema = spec["components"]["schemas"]["JobSummary"]["properties"]["created_at"]
    assert schema["format"] == "date-time" and schema["type"] == "string"
    assert record["status"] == "succeeded"
