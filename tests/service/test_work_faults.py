"""Faults around the work: a store that refuses writes, workers killed, graceful restarts, starvation."""
import concurrent.futures as cf
import logging
import os
import signal
import time

import pytest
from fastapi.testclient import TestClient
from sqlalchemy import event, text

from greyfit.service.http.app import create_app
from greyfit.service.jobs.store import JobStore, make_engine
from tests.service.conftest import assert_problem, make_settings, msd_request, slow_request, wait_for_job


def wait_until(condition, timeout=60.0, what="condition"):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = condition()
        if value:
            return value
        time.sleep(0.02)
    raise AssertionError(f"{what} not reached in {timeout} s")


def running_task(client, job_id):
    return wait_until(lambda: any(t["status"] == "running" for t in client.get(f"/v1/jobs/{job_id}").json()["tasks"]),
                      what="a running task")


def make_read_only(engine, on: bool) -> None:
    """A real fault, not a mock: new connections of the server's own engine refuse writes."""
    def read_only(dbapi_conn, _record):
        cur = dbapi_conn.cursor()
        if engine.dialect.name == "sqlite":
            cur.execute("PRAGMA query_only = ON")
        else:
            cur.execute("SET default_transaction_read_only = on")
            dbapi_conn.commit()
        cur.close()

    if on:
        event.listen(engine, "connect", read_only)
        engine._greyfit_read_only = read_only
    else:
        event.remove(engine, "connect", engine._greyfit_read_only)
    engine.dispose()   # pooled connections are replaced by ones made under the new rule


def test_a_result_that_cannot_be_written_is_written_when_the_store_recovers(tmp_path):
    """Defect: the task left the running list before its outcome was stored, so it stayed 'running'."""
    with TestClient(create_app(make_settings(tmp_path, workers=1))) as c:
        store = c.app.state.store
        with store.engine.begin() as conn:   # every write that ends a task fails for now
            conn.execute(text("CREATE TRIGGER refuse_finish BEFORE UPDATE OF status ON tasks "
                              "WHEN NEW.status IN ('succeeded', 'failed') "
                              "BEGIN SELECT RAISE(ABORT, 'simulated: the store refuses writes'); END"))
        job_id = c.post("/v1/jobs", json={"requests": [msd_request(0, n=41)]}).json()["id"]
        wait_until(lambda: 'greyfit_fits_total{kind="fit",status="succeeded"} 1' in c.get("/metrics").text,
                   what="the fit finished")
        time.sleep(0.5)                       # several dispatcher rounds fail to write it
        assert c.get(f"/v1/jobs/{job_id}").json()["status"] == "running"
        with store.engine.begin() as conn:
            conn.execute(text("DROP TRIGGER refuse_finish"))
        job = wait_for_job(c, job_id, timeout=20)
        assert job["status"] == "succeeded" and job["tasks"][0]["attempts"] == 1
        result = c.get(f"/v1/jobs/{job_id}/results").json()["results"][0]["result"]
        assert result["parameters"]["k"]["value"] == pytest.approx(5.0, rel=0.05)


def test_a_deleted_sqlite_file_makes_the_server_unready_and_refuse_jobs(tmp_path):
    with TestClient(create_app(make_settings(tmp_path, workers=1))) as c:
        assert c.get("/readyz").status_code == 200
        for suffix in ("", "-wal", "-shm"):
            if os.path.exists(tmp_path / f"greyfit.db{suffix}"):
                os.remove(tmp_path / f"greyfit.db{suffix}")
        assert_problem(c.get("/readyz"), 503, "deleted or replaced")
        resp = c.post("/v1/jobs", json={"requests": [msd_request(0, n=41)]})
        assert_problem(resp, 503, "deleted or replaced", "restart the server")
        assert resp.headers["retry-after"]


def test_a_read_only_store_is_503_and_unready_then_recovers(store_url, tmp_path):
    with TestClient(create_app(make_settings(tmp_path, workers=1, database_url=store_url))) as c:
        engine = c.app.state.store.engine
        make_read_only(engine, True)
        try:
            assert_problem(c.get("/readyz"), 503, "does not take writes")
            resp = c.post("/v1/jobs", json={"requests": [msd_request(0, n=41)]})
            assert_problem(resp, 503, "job store")
            assert "read" in resp.json()["detail"].lower()
        finally:
            make_read_only(engine, False)
        assert c.get("/readyz").status_code == 200
        job_id = c.post("/v1/jobs", json={"requests": [msd_request(0, n=41)]}).json()["id"]
        assert wait_for_job(c, job_id)["status"] == "succeeded"


def started_task(client, job_id):
    """Wait until a worker has acknowledged the start of the job's first task (its attempt is charged)."""
    return wait_until(lambda: client.get(f"/v1/jobs/{job_id}").json()["tasks"][0]["started_at"],
                      what="a started task")


def test_a_worker_killed_mid_task_is_retried_not_called_a_cpu_limit(tmp_path):
    with TestClient(create_app(make_settings(tmp_path, workers=1))) as c:
        job_id = c.post("/v1/jobs", json={"requests": [slow_request()]}).json()["id"]
        started_task(c, job_id)
        time.sleep(0.2)
        os.kill(c.app.state.dispatcher.executor.slots[0].process.pid, signal.SIGKILL)
        job = wait_for_job(c, job_id)
        assert job["status"] == "succeeded", job
        assert job["tasks"][0]["attempts"] == 2          # the lost start counted, the retry succeeded
        assert "CPU" not in str(job["tasks"][0]["error"])


def test_three_graceful_restarts_during_one_task_do_not_fail_it(tmp_path):
    settings = make_settings(tmp_path, workers=1, task_max_attempts=3)
    with TestClient(create_app(settings)) as c:
        job_id = c.post("/v1/jobs", json={"requests": [slow_request()]}).json()["id"]
        running_task(c, job_id)
    for _ in range(3):                                   # SIGTERM-like: the lifespan ends, tasks handed back
        with TestClient(create_app(settings)) as c:
            assert c.get(f"/v1/jobs/{job_id}").json()["tasks"][0]["attempts"] <= 1   # just re-claimed, or not yet
            running_task(c, job_id)
    with TestClient(create_app(settings)) as c:
        job = wait_for_job(c, job_id)
        assert job["status"] == "succeeded", job
        assert job["tasks"][0]["attempts"] == 1


def short_job(n: int) -> dict:
    """Tasks of milliseconds: the dispatcher claims them ahead and queues one behind each worker's."""
    fit = msd_request(0, n=41)
    fit["method"] = "equation_error"
    return {"requests": [fit] * n}


def wait_for_claims_ahead(c, job_id: str, done: int = 20) -> None:
    dispatcher, deadline = c.app.state.dispatcher, time.monotonic() + 120
    while time.monotonic() < deadline:
        if len(dispatcher.ready) > 0 and c.get(f"/v1/jobs/{job_id}").json()["progress"]["done"] >= done:
            return
        time.sleep(0.005)
    raise AssertionError("no tasks were claimed ahead")


def test_cancelling_a_job_of_short_tasks_drops_the_tasks_claimed_ahead(client):
    job_id = client.post("/v1/jobs", json=short_job(600)).json()["id"]
    wait_for_claims_ahead(client, job_id)
    client.delete(f"/v1/jobs/{job_id}")
    job = wait_for_job(client, job_id)
    statuses = [t["status"] for t in job["tasks"]]
    assert job["status"] == "cancelled" and set(statuses) <= {"succeeded", "cancelled"}
    assert statuses.count("succeeded") >= 20 and statuses.count("cancelled") >= 100
    dispatcher = client.app.state.dispatcher
    assert not any(t.job_id == job_id for t in dispatcher.ready)
    assert not any(item.job_id == job_id for item in dispatcher.running.values())


def test_a_graceful_stop_hands_back_the_tasks_claimed_ahead_without_counting_a_start(tmp_path):
    settings = make_settings(tmp_path, workers=2)
    with TestClient(create_app(settings)) as c:
        job_id = c.post("/v1/jobs", json=short_job(600)).json()["id"]
        wait_for_claims_ahead(c, job_id)
    store = JobStore(make_engine(settings.resolved_database_url()))
    try:
        tasks = store.get_job(job_id)["tasks"]
    finally:
        store.engine.dispose()
    assert {t["status"] for t in tasks} <= {"succeeded", "queued"}
    assert all(t["attempts"] == (t["status"] == "succeeded") for t in tasks)
    with TestClient(create_app(settings)) as c:             # the next server runs the rest, once each
        job = wait_for_job(c, job_id, timeout=180)
    assert job["progress"] == {"done": 600, "total": 600, "succeeded": 600, "failed": 0}
    assert all(t["attempts"] == 1 for t in job["tasks"])


def test_a_worker_traceback_is_logged_with_the_task(client, caplog):
    caplog.set_level(logging.ERROR, logger="greyfit.dispatcher")
    fut = client.app.state.dispatcher.submit_sync("no-such-kind", {})
    outcome = fut.result(timeout=60)
    assert outcome.error.type == "InternalError"
    logged = "\n".join(r.getMessage() for r in caplog.records)
    assert "internal error" in logged and "sync-" in logged and "KeyError" in logged and "Traceback" in logged


def sync_done_when_the_job_starts(dispatcher, job_id: str, burst: list, timeout: float = 60) -> int:
    """How many of `burst` had finished when a task of `job_id` reached a worker: an order, not a
    duration, so a slow first fit or the status poll's 0.1 s does not count against the scheduler."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        done = sum(f.done() for f in burst)
        if any(item.job_id == job_id for item in list(dispatcher.running.values())):
            return done
        time.sleep(0.001)
    raise AssertionError(f"no task of job {job_id} started in {timeout} s")


def test_jobs_progress_under_a_burst_of_synchronous_fits(tmp_path):
    """Defect: a job task waited behind every queued synchronous fit."""
    with TestClient(create_app(make_settings(tmp_path, workers=2))) as c:
        dispatcher = c.app.state.dispatcher
        bodies, job = [msd_request(i) for i in range(40)], {"requests": [msd_request(99, n=41)]}
        burst = [dispatcher.submit_sync("fit", body) for body in bodies]
        job_id = c.post("/v1/jobs", json=job).json()["id"]
        done_before = sync_done_when_the_job_starts(dispatcher, job_id, burst)
        print(f"synchronous fits done when the job task started: {done_before} of 40")
        job = wait_for_job(c, job_id)
        assert job["status"] == "succeeded"
        assert done_before <= 10, f"the job waited for {done_before} of 40 synchronous fits"
        outcomes = [f.result(timeout=120) for f in cf.as_completed(burst, timeout=180)]
        assert all(o.status == "succeeded" for o in outcomes)


def test_three_server_deaths_right_after_a_claim_do_not_fail_the_task(tmp_path):
    """Defect: the claim charged the attempt, so three servers that died between their claim and
    the start failed the task 'lost 3 times' with 0 executions."""
    settings = make_settings(tmp_path, workers=1, task_max_attempts=3)
    store = JobStore(make_engine(settings.resolved_database_url()))
    try:
        job_id = store.create_job("fit", [msd_request(0, n=41)], None)
        for i in range(3):            # each server claimed the task, then died before a worker had it
            assert store.claim(f"dead-server-{i}", 0.01, settings.task_max_attempts) is not None
            time.sleep(0.02)
            assert store.requeue_expired() == 1   # what the next server does when it starts
    finally:
        store.engine.dispose()
    with TestClient(create_app(settings)) as c:   # starting, it re-queues the expired leases
        job = wait_for_job(c, job_id)
    assert job["status"] == "succeeded", job
    assert job["tasks"][0]["attempts"] == 1 and job["tasks"][0]["started_at"] is not None


def test_a_stopped_worker_is_a_lost_worker_retried_not_a_timeout(tmp_path):
    """Defect: a worker frozen by SIGSTOP mid-task ran into the wall-time limit: the task failed as
    `Timeout`, not retried. Its CPU clock stands still: it is replaced and the task runs again."""
    settings = make_settings(tmp_path, workers=1, worker_stall_seconds=1.5, task_wall_seconds=20.0)
    with TestClient(create_app(settings)) as c:
        job_id = c.post("/v1/jobs", json={"requests": [slow_request()]}).json()["id"]
        started_task(c, job_id)
        pid = c.app.state.dispatcher.executor.slots[0].process.pid
        os.kill(pid, signal.SIGSTOP)
        try:
            job = wait_for_job(c, job_id, timeout=120)
        finally:
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
    assert job["status"] == "succeeded", job
    assert job["tasks"][0]["attempts"] == 2           # the stopped start counted, the retry succeeded
    assert "Timeout" not in str(job["tasks"][0]["error"])


def test_a_synchronous_fit_whose_worker_dies_is_503_with_retry_after(tmp_path):
    """Defect: the 503 of a lost worker had no Retry-After, which every 503 is documented to carry."""
    with TestClient(create_app(make_settings(tmp_path, workers=1, retry_after_seconds=3))) as c:
        executor = c.app.state.dispatcher.executor
        with cf.ThreadPoolExecutor(1) as pool:
            answer = pool.submit(c.post, "/v1/fits", json=slow_request())
            slot = wait_until(lambda: next((s for s in executor.slots if s.keys), None), what="the fit on a worker")
            wait_until(lambda: not executor._started and slot.started, what="the fit's start")
            time.sleep(0.1)                                # mid-fit: the fit takes about a second
            os.kill(slot.process.pid, signal.SIGKILL)
            resp = answer.result(timeout=120)
    assert_problem(resp, 503, "worker", "retry")
    assert resp.headers["retry-after"] == "3"
