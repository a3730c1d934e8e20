"""Dask at the edges: a task's wall clock starts on a worker, and a killed scheduler costs no task.

Real clusters: a LocalCluster for the wall clock, and for the restart a `dask scheduler` process
that is killed (SIGKILL) and started again on the same port, with a worker of
`python -m greyfit.service.dask_worker`, which outlives its scheduler.
"""
import socket
import subprocess
import sys
import time

import pytest
from fastapi.testclient import TestClient

from greyfit.service.http.app import create_app
from tests.servers import free_port
from tests.service.conftest import make_settings, msd_request, wait_for_job
from tests.systems import MSD_TRUTH

distributed = pytest.importorskip("distributed")

K_TRUE = MSD_TRUTH["k"]   # the stiffness msd_request's data were simulated with


def _until(predicate, seconds: float, what: str):
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.2)
    raise AssertionError(f"{what}: not within {seconds} s")


def _assert_all_succeeded_once(c, job_id: str, n: int) -> dict:
    job = wait_for_job(c, job_id, timeout=240)
    assert job["status"] == "succeeded", job
    results = c.get(f"/v1/jobs/{job_id}/results").json()["results"]
    assert [r["index"] for r in results] == list(range(n))          # one stored result per task
    assert [r["status"] for r in results] == ["succeeded"] * n
    for r in results:
        assert abs(r["result"]["parameters"]["k"]["value"] / K_TRUE - 1) < 0.02
    return job


@pytest.mark.slow
def test_a_task_waiting_for_a_dask_worker_is_not_timed_out(tmp_path):
    """Defect: the wall clock ran from submission, so tasks queued behind a busy worker failed as
    `Timeout` without having run. The only worker thread is held for 2.5x the wall-time limit; the
    job's tasks wait that long and still succeed, each charged one attempt (its one start)."""
    from greyfit.service.jobs.tasks import run_task

    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address=None) as cluster:
        wall = 8.0
        settings = make_settings(tmp_path, executor="dask", dask_scheduler=cluster.scheduler_address,
                                 task_wall_seconds=wall)
        with distributed.Client(cluster.scheduler_address, set_as_default=False) as other:
            # warm the worker (CasADi's import, the model's compiled functions) without a wall-time
            # limit, so that the job's fits are short beside it on a loaded machine
            warm = other.submit(run_task, "fit", msd_request(0, n=41), 600.0, pure=False).result()
            assert warm.status == "succeeded"
            with TestClient(create_app(settings)) as c:
                blocker = other.submit(time.sleep, 2.5 * wall, pure=False)
                _until(lambda: other.processing() and any(other.processing().values()), 30, "the blocker runs")
                n = 3
                job_id = c.post("/v1/jobs", json={"requests": [msd_request(i, n=41) for i in range(n)]}).json()["id"]
                job = _assert_all_succeeded_once(c, job_id, n)
                assert blocker.done()
                assert [t["attempts"] for t in job["tasks"]] == [1] * n


@pytest.fixture
def scheduler_port():
    return free_port()


def _start_scheduler(port: int, log) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "distributed.cli.dask_scheduler", "--host", "127.0.0.1",
                             "--port", str(port), "--no-dashboard"], stdout=log, stderr=subprocess.STDOUT)


def _accepts(port: int) -> bool:
    try:
        socket.create_connection(("127.0.0.1", port), timeout=1).close()
        return True
    except OSError:
        return False


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(15)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)


@pytest.mark.slow
def test_a_killed_dask_scheduler_costs_no_task_and_the_job_resumes_by_itself(tmp_path, scheduler_port):
    """Defect: after a scheduler restart jobs resumed only when new workers appeared, and the client
    gave up on its scheduler for good after its timeout. Now: scheduler killed -> /readyz 503 naming
    it, a synchronous fit 503 + Retry-After at once; scheduler back (after the client's own
    reconnection gave up) -> the same worker registers again, the job finishes, every task
    succeeded, one result each."""
    address = f"tcp://127.0.0.1:{scheduler_port}"
    log = open(tmp_path / "cluster.log", "ab")
    scheduler = _start_scheduler(scheduler_port, log)
    worker = subprocess.Popen([sys.executable, "-m", "greyfit.service.dask_worker", address, "--nthreads", "1"],
                              stdout=log, stderr=subprocess.STDOUT)
    try:
        _until(lambda: _accepts(scheduler_port), 60, "the scheduler listens")
        settings = make_settings(tmp_path, executor="dask", dask_scheduler=address, dask_connect_seconds=3.0,
                                 task_wall_seconds=600.0)
        app = create_app(settings)
        with TestClient(app) as c:
            executor = app.state.dispatcher.executor
            first_client = executor.client
            _until(lambda: c.get("/readyz").status_code == 200, 60, "ready with a worker")
            n = 8
            job_id = c.post("/v1/jobs", json={"requests": [msd_request(i, n=201) for i in range(n)]}).json()["id"]
            _until(lambda: c.get(f"/v1/jobs/{job_id}").json()["progress"]["done"] >= 1, 120, "a first task done")

            scheduler.kill()
            scheduler.wait(10)
            down = _until(lambda: (r := c.get("/readyz")).status_code == 503 and r, 30, "readiness says so")
            assert "Dask scheduler" in down.json()["detail"] and int(down.headers["retry-after"]) >= 1
            fit = c.post("/v1/fits", json=msd_request(0, n=41))   # refused now, not after the wall-time limit
            assert fit.status_code == 503 and int(fit.headers["retry-after"]) >= 1, fit.text
            time.sleep(2 * settings.dask_connect_seconds)   # past the client's own reconnection: it gives up
            assert c.get("/readyz").status_code == 503
            assert c.get(f"/v1/jobs/{job_id}").json()["progress"]["failed"] == 0

            scheduler = _start_scheduler(scheduler_port, log)
            _until(lambda: c.get("/readyz").status_code == 200, 90, "ready again with the same worker")
            job = _assert_all_succeeded_once(c, job_id, n)
            assert all(1 <= t["attempts"] <= 2 for t in job["tasks"]), job["tasks"]
            assert worker.poll() is None          # the one worker process outlived its scheduler
            assert executor.client is not first_client   # the client that gave up was replaced
    finally:
        _stop(worker)
        _stop(scheduler)
        log.close()
