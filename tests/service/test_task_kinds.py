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
    from greyfit.service import cli_service, tasks
    assert set(tasks._runners()) == set(TASK_KINDS)
    assert client_module.JOB_KINDS == cli_service.JOB_KINDS == JOB_KINDS
    spec = client.get("/openapi.json").json()
    assert spec["components"]["schemas"]["JobPublic"]["properties"]["kind"]["enum"] == list(JOB_KINDS)
    for kind in KINDS.values():
        for path in (kind.sync_path, kind.jobs_path):
            if path and kind.generate:
                assert "post" in spec["paths"][path], path
    assert "kind" in JobPublic.model_fields


def test_a_kind_without_jobs_says_so():
    import pytest
    with pytest.raises(LookupError, match="takes no jobs"):
        KINDS["simulate"].job_schema()
