"""Against a real `greyfit serve` process on loopback: kill -9 mid-job, restart, nothing lost."""
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from tests.service.conftest import msd_request, slow_request

ROOT = Path(__file__).resolve().parents[2]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_server(data_dir: Path, port: int, workers: int = 2, log: Path | None = None,
                 **env_overrides: str) -> subprocess.Popen:
    """A `greyfit serve` subprocess, ready; its output goes to `log` when given, else nowhere."""
    env = {**os.environ, "GREYFIT_LEASE_SECONDS": "2", "GREYFIT_POLL_SECONDS": "0.02", **env_overrides}
    out = open(log, "ab") if log is not None else subprocess.DEVNULL
    try:
        proc = subprocess.Popen([sys.executable, "-m", "greyfit.service.cli", "serve", "--host", "127.0.0.1",
                                 "--port", str(port), "--data-dir", str(data_dir), "--workers", str(workers)],
                                cwd=ROOT, env=env, start_new_session=True, stdout=out, stderr=subprocess.STDOUT)
    finally:
        if log is not None:
            out.close()   # the child holds its own descriptor
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            if httpx.get(f"http://127.0.0.1:{port}/readyz", timeout=1).status_code == 200:
                return proc
        except httpx.HTTPError:
            pass
        if proc.poll() is not None:
            raise AssertionError(f"server exited with {proc.returncode}")
        time.sleep(0.2)
    os.killpg(proc.pid, signal.SIGKILL)
    raise AssertionError("server did not become ready")


def wait_until_finished(base: str, job_id: str, timeout: float = 180) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        job = httpx.get(f"{base}/v1/jobs/{job_id}").json()
        if job["status"] not in ("queued", "running"):
            return job
        time.sleep(0.2)
    raise AssertionError(f"job {job_id} did not finish in {timeout} s: {job}")


def stop_server(server: subprocess.Popen) -> None:
    server.send_signal(signal.SIGTERM)
    try:
        server.wait(timeout=20)
    except subprocess.TimeoutExpired:
        os.killpg(server.pid, signal.SIGKILL)


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
