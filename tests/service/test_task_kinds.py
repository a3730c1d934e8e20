"""The task-kind table is the one place a kind is named: workers, routes, jobs, CLI batch and client read it."""
import pickle

from greyfit.schemas.jobs import JobPublic
from greyfit.service.task_kinds import JOB_KINDS, KINDS, TASK_KINDS


def test_every_kind_loads_its_schemas_and_runner():
    for kind in KINDS.values():
        assert kind.request_schema().__name__.endswith("Request")
        assert callable(kind.runner())
        assert kind.result_schema().model_json_schema()["type"] == "object"
        if kind.jobs_path:
            body = kind.job_schema()
            # the body parser processes receive the class by reference (module + name)
            assert pickle.loads(pickle.dumps(body)) is body
            assert body.model_fields["requests"].annotation == list[kind.request_schema()]


def test_workers_routes_cli_and_client_offer_the_same_kinds(client):
    from greyfit import client as client_module
    from greyfit.service.cli import serve as cli_service
    from greyfit.service.jobs import tasks
    assert set(tasks._runners()) == set(TASK_KINDS)
    assert client_module.JOB_KINDS == cli_service.JOB_KINDS == JOB_KINDS
    spec = client.get("/openapi.json").json()
    assert spec["components"]["schemas"]["JobPublic"]["properties"]["kind"]["enum"] == list(JOB_KINDS)
    for kind in KINDS.values():
        for path in (kind.sync_path, kind.jobs_path):
            if path:   # generated, or (generate=False) the hand-written route the entry names
                assert "post" in spec["paths"][path], path
    assert "kind" in JobPublic.model_fields


def test_a_kind_without_jobs_says_so():
    import pytest
    with pytest.raises(LookupError, match="takes no jobs"):
        KINDS["simulate"].job_schema()


def test_every_generated_sync_route_documents_an_example_from_its_entry(client):
    # the OpenAPI "Try it out" body, and the body tests/service/test_openapi_answers.py sends
    spec = client.get("/openapi.json").json()
    for kind in KINDS.values():
        assert kind.example is not None or not (kind.generate and kind.sync_path), kind.name
        if kind.example is not None:
            kind.request_schema().model_validate(kind.example.build())
        if kind.job_example is not None:
            kind.job_schema().model_validate(kind.job_example.build())
        for path, example in ((kind.sync_path, kind.example), (kind.jobs_path, kind.job_example)):
            if example is not None:
                body = spec["paths"][path]["post"]["requestBody"]["content"]["application/json"]
                assert list(body["examples"]) == [example.name], path
