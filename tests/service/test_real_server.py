"""Against a real `greyfit serve` process on loopback: kill -9 mid-job, restart, nothing lost."""
import os
import signal
import time
from pathlib import Path

import httpx
import pytest

from tests.servers import free_port, msd_request, slow_request, start_server, stop_server, wait_until_finished  # noqa: F401

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_kill_9_mid_job_restart_and_every_task_finishes_exactly_once(tmp_path):
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    server = start_server(tmp_path, port)
    try:
        resp = httpx.post(f"{base}/v1/jobs", json={"requests": [slow_request() for _ in range(8)]}, timeout=30)
        assert resp.status_code == 202
        job_id = resp.json()["id"]
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            job = httpx.get(f"{base}/v1/jobs/{job_id}").json()
            running = sum(t["status"] == "running" for t in job["tasks"])
            if job["progress"]["done"] >= 1 and running >= 1:
                break
            time.sleep(0.05)
        done_before = job["progress"]["done"]
        assert done_before < 8, "the job finished before the kill; make the tasks slower"
        os.killpg(server.pid, signal.SIGKILL)      # the server and its worker processes
        server.wait(timeout=10)

        server = start_server(tmp_path, port)
        job = wait_until_finished(base, job_id)
        assert job["status"] == "succeeded", job
        assert job["progress"] == {"done": 8, "total": 8, "succeeded": 8, "failed": 0}
        assert any(t["attempts"] == 2 for t in job["tasks"]), "no task was re-run after the kill"
        results = httpx.get(f"{base}/v1/jobs/{job_id}/results").json()["results"]
        assert [r["index"] for r in results] == list(range(8))
        assert all(r["status"] == "succeeded" and r["result"]["success"] for r in results)
        # and the restarted server serves new work
        assert httpx.post(f"{base}/v1/fits", json=msd_request(1), timeout=60).status_code == 200
    finally:
        stop_server(server)


@pytest.mark.slow
def test_two_replicas_share_one_store_and_run_each_task_once(tmp_path):
    """Two servers on one job store: both take tasks, none is run twice."""
    import sqlite3
    ports = [free_port(), free_port()]
    servers = [start_server(tmp_path, port) for port in ports]
    try:
        resp = httpx.post(f"http://127.0.0.1:{ports[0]}/v1/jobs",
                          json={"requests": [msd_request(i, n=1001) for i in range(16)]}, timeout=30)
        job = wait_until_finished(f"http://127.0.0.1:{ports[1]}", resp.json()["id"])
        job_id = job["id"]
        assert job["status"] == "succeeded" and job["progress"]["succeeded"] == 16
        assert all(t["attempts"] == 1 for t in job["tasks"])       # nobody ran a task twice
        with sqlite3.connect(tmp_path / "greyfit.db") as db:
            owners = {row[0] for row in db.execute("SELECT owner FROM tasks WHERE job_id = ?", (job_id,))}
        assert len(owners) == 2, owners                           # both replicas worked
    finally:
        for server in servers:
            stop_server(server)
