"""Against real `greyfit serve` processes: clients that hang up, and a PostgreSQL replica killed mid-job."""
import os
import re
import signal
import threading
import time

import httpx
import pytest

from tests.service.conftest import msd_request, slow_request
from tests.service.test_real_server import free_port, start_server, stop_server, wait_until_finished


def fits_counted(base: str, status: str) -> int:
    match = re.search(rf'greyfit_fits_total{{kind="fit",status="{status}"}} (\d+)', httpx.get(f"{base}/metrics").text)
    return int(match.group(1)) if match else 0


@pytest.mark.slow
def test_clients_that_hang_up_free_their_workers(tmp_path):
    """Defect: uvicorn does not cancel the handler of a client that left, so its fit ran to the end."""
    port = free_port()
    base = f"http://127.0.0.1:{port}"
    server = start_server(tmp_path, port, workers=1)
    try:
        long_fit = slow_request()
        long_fit["options"]["multistart"] = 40          # tens of seconds each if nobody stops it
        errors = []

        def impatient():
            try:
                httpx.post(f"{base}/v1/fits", json=long_fit, timeout=1.0)
            except httpx.TimeoutException:               # the client gives up and closes the connection
                return
            errors.append("the fit answered within 1 s")

        clients = [threading.Thread(target=impatient) for _ in range(4)]
        for t in clients:
            t.start()
        for t in clients:
            t.join(timeout=30)
        assert not errors
        deadline = time.monotonic() + 30
        while fits_counted(base, "abandoned") < 4 and time.monotonic() < deadline:
            time.sleep(0.2)
        assert fits_counted(base, "abandoned") == 4     # the running one stopped, the queued ones dropped
        resp = httpx.post(f"{base}/v1/fits", json=msd_request(0), timeout=60)
        assert resp.status_code == 200 and resp.json()["success"]
        assert fits_counted(base, "succeeded") == 1     # none of the abandoned fits ran to its end
    finally:
        stop_server(server)


@pytest.mark.slow
def test_two_postgres_replicas_one_killed_mid_job_every_task_finished_once(tmp_path, postgres_url):
    ports = [free_port(), free_port()]
    env = {"GREYFIT_DATABASE_URL": postgres_url}
    servers = [start_server(tmp_path / f"r{i}", port, workers=1, **env) for i, port in enumerate(ports)]
    bases = [f"http://127.0.0.1:{p}" for p in ports]
    try:
        job_id = httpx.post(f"{bases[0]}/v1/jobs", json={"requests": [slow_request() for _ in range(6)]},
                            timeout=30).json()["id"]
        deadline = time.monotonic() + 60
        # both replicas are working on it, and both starts are on record: a start is written with the
        # dispatcher's next batch of outcomes, and a server killed before that was never charged one
        while time.monotonic() < deadline:
            tasks = httpx.get(f"{bases[1]}/v1/jobs/{job_id}").json()["tasks"]
            if sum(t["status"] == "running" and t["attempts"] >= 1 for t in tasks) == 2:
                break
            time.sleep(0.05)
        os.killpg(servers[0].pid, signal.SIGKILL)       # replica 0 and its worker, mid-task
        servers[0].wait(timeout=10)
        job = wait_until_finished(bases[1], job_id)
        assert job["status"] == "succeeded", job
        assert job["progress"] == {"done": 6, "total": 6, "succeeded": 6, "failed": 0}
        attempts = sorted(t["attempts"] for t in job["tasks"])
        assert attempts[-1] == 2 and attempts.count(2) == 1, attempts   # only the killed task ran again
        results = httpx.get(f"{bases[1]}/v1/jobs/{job_id}/results").json()["results"]
        assert [r["index"] for r in results] == list(range(6))
        for r in results:
            assert r["result"]["parameters"]["k"]["value"] == pytest.approx(5.0, rel=0.02)
    finally:
        for server in servers:
            if server.poll() is None:
                stop_server(server)
