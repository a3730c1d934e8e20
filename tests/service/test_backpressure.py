"""Back-pressure and what /metrics shows (issue 41, item 5): a limit on the job store's queued
tasks (503 with Retry-After, nothing accepted lost; SQLite and PostgreSQL), and Prometheus metrics
through prometheus_client with the process's own, the queues, lost workers and give-backs."""
import os
import signal
import time

import pytest
from fastapi.testclient import TestClient
from prometheus_client.parser import text_string_to_metric_families

from greyfit.service.http.app import create_app
from tests.service.conftest import assert_problem, make_settings, msd_request, slow_request, wait_for_job


def samples(client) -> dict[tuple[str, tuple], float]:
    resp = client.get("/metrics")
    assert resp.status_code == 200 and resp.headers["content-type"].startswith("text/plain")
    return {(s.name, tuple(sorted(s.labels.items()))): s.value
            for family in text_string_to_metric_families(resp.text) for s in family.samples}


def test_metrics_show_the_process_the_queues_and_the_executor(client):
    seen = samples(client)
    names = {name for name, _ in seen}
    assert {"process_resident_memory_bytes", "process_cpu_seconds_total", "greyfit_sync_queue_depth",
            "greyfit_tasks_running", "greyfit_queue_depth"} <= names
    assert seen[("greyfit_executor_ready", (("executor", "LocalWorkerPool"),))] == 1.0
    assert seen[("greyfit_executor_capacity", (("executor", "LocalWorkerPool"),))] == 2.0
    assert seen[("greyfit_store_tasks", (("status", "queued"),))] >= 0
    assert seen[("process_resident_memory_bytes", ())] > 10e6


def test_the_queued_task_limit_answers_503_and_loses_nothing(tmp_path, store_url):
    settings = make_settings(tmp_path, workers=1, database_url=store_url, max_queued_tasks=4)
    with TestClient(create_app(settings)) as c:
        # the slow task holds the one worker while the three behind it wait (one may be claimed ahead):
        # at least two are queued when the next job comes, and 2 + 3 > 4
        first = c.post("/v1/jobs", json={"requests": [slow_request()] + [msd_request(0, n=41)] * 3})
        assert first.status_code == 202, first.text
        refused = c.post("/v1/jobs", json={"requests": [msd_request(1, n=41)] * 3})
        assert_problem(refused, 503, "GREYFIT_MAX_QUEUED_TASKS")
        assert int(refused.headers["retry-after"]) >= 1
        assert_problem(c.post("/v1/jobs", json={"requests": [msd_request(1, n=41)] * 5}), 422,
                       "GREYFIT_MAX_QUEUED_TASKS")
        assert samples(c)[("greyfit_refused_total", (("limit", "queued_tasks"),))] == 1.0
        job = wait_for_job(c, first.json()["id"], timeout=300)
        assert [t["status"] for t in job["tasks"]] == ["succeeded"] * 4
        second = c.post("/v1/jobs", json={"requests": [msd_request(1, n=41)] * 3})   # the retry, later
        assert second.status_code == 202
        assert wait_for_job(c, second.json()["id"])["status"] == "succeeded"
        listed = c.get("/v1/jobs").json()
        assert listed["count"] == 2        # the refused job stored nothing


def test_a_lost_worker_is_counted_replaced_and_its_task_given_back(tmp_path):
    with TestClient(create_app(make_settings(tmp_path, workers=1))) as c:
        job_id = c.post("/v1/jobs", json={"requests": [slow_request()]}).json()["id"]
        executor = c.app.state.dispatcher.executor
        deadline = time.monotonic() + 60
        while c.get(f"/v1/jobs/{job_id}").json()["tasks"][0]["attempts"] == 0:
            assert time.monotonic() < deadline, "the task never started"
            time.sleep(0.05)
        os.kill(executor.slots[0].process.pid, signal.SIGKILL)
        job = wait_for_job(c, job_id, timeout=300)
        assert job["status"] == "succeeded" and job["tasks"][0]["attempts"] == 2
        seen = samples(c)
    assert seen[("greyfit_worker_losses_total", (("kind", "fit"),))] == 1.0
    assert seen[("greyfit_worker_replacements", (("executor", "LocalWorkerPool"),))] == 1.0
    assert seen[("greyfit_task_give_backs_total", (("reason", "lost_worker"),))] == 1.0


@pytest.fixture(scope="module")
def client(module_tmp):
    with TestClient(create_app(make_settings(module_tmp))) as c:
        yield c
