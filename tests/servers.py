"""Fixtures shared by the real-server tests and the benchmarks: a `greyfit serve` process on
loopback, its requests, probes of its health while it works."""
import asyncio
import copy
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from datetime import datetime
from pathlib import Path

import httpx
import numpy as np

from tests.systems import msd_experiment, msd_model, simulate_msd

ROOT = Path(__file__).resolve().parents[1]


def msd_request(seed: int, noise: float = 0.005, n: int = 101) -> dict:
    t = np.linspace(0, 10, n)
    return {"model": msd_model(c=0.5, k=3.0), "method": "multiple_shooting",
            "experiments": [msd_experiment(t, simulate_msd(t), noise=noise, seed=seed)]}


def slow_request() -> dict:
    """About a second of work: a 2001-sample output-error fit with several starts."""
    body = msd_request(0, n=2001)
    body["options"] = {"multistart": 4, "substeps": 4}
    return copy.deepcopy(body)


def long_fit() -> dict:
    """A fit of a minute or more: 100 starts of an 8001-sample output-error fit (~0.4 CPU-s each)."""
    body = msd_request(0, n=8001)
    body["options"] = {"multistart": 100, "substeps": 4}
    return body


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


def children_of(pid: int) -> set[int]:
    """The live processes whose parent is `pid` (from /proc; Linux)."""
    from greyfit.service.jobs.lifeline import start_time
    found = set()
    for entry in os.listdir("/proc"):
        if entry.isdigit() and start_time(int(entry)) is not None:
            try:
                with open(f"/proc/{entry}/stat", "rb") as f:
                    if int(f.read().rsplit(b")", 1)[1].split()[1]) == pid:
                        found.add(int(entry))
            except (OSError, IndexError):
                pass
    return found


def alive(pids: set[int]) -> set[int]:
    """Those of `pids` still running (a zombie has ended)."""
    from greyfit.service.jobs.lifeline import start_time
    return {p for p in pids if start_time(p) is not None}


def wait_gone(pids: set[int], bound: float = 30.0) -> set[int]:
    """Poll until every process of `pids` has ended or `bound` seconds passed; those left. The
    bound is generous: it is a liveness bound, not a measure of speed."""
    deadline = time.monotonic() + bound
    while alive(pids) and time.monotonic() < deadline:
        time.sleep(0.05)
    return alive(pids)


def wait_running(base: str, job_id: str, attempts: int, timeout: float = 120) -> list[dict]:
    """Poll until every task of the job runs, its start acknowledged `attempts` times; the tasks."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        tasks = httpx.get(f"{base}/v1/jobs/{job_id}").json()["tasks"]
        if all(t["status"] == "running" and t["attempts"] == attempts for t in tasks):
            break
        time.sleep(0.2)
    return tasks


def wait_until_finished(base: str, job_id: str, timeout: float = 180) -> dict:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        job = httpx.get(f"{base}/v1/jobs/{job_id}").json()
        if job["status"] not in ("queued", "running"):
            return job
        time.sleep(0.2)
    raise AssertionError(f"job {job_id} did not finish in {timeout} s: {job}")


def unix_time(stamp: str) -> float:
    """A job record's RFC 3339 timestamp (`finished_at`, ...) as Unix time, to set beside time.time()."""
    return datetime.fromisoformat(stamp.replace("Z", "+00:00")).timestamp()


def stop_server(server: subprocess.Popen) -> None:
    server.send_signal(signal.SIGTERM)
    try:
        server.wait(timeout=20)
    except subprocess.TimeoutExpired:
        os.killpg(server.pid, signal.SIGKILL)


def large_fit_request(megabytes: float) -> dict:
    """A fit request whose four time series make the body about this large."""
    n = int(megabytes * 2 ** 20 / 80)
    t = np.arange(n) * 1e-3
    body = msd_request(0, n=11)
    exp = body["experiments"][0]
    exp["time"] = t.tolist()
    exp["inputs"] = {"u": np.sin(t).tolist()}
    exp["outputs"] = {"x": np.cos(t).tolist(), "v": np.sin(t).tolist()}
    return body


def probe_healthz(base: str, stop: threading.Event, every: float = 0.025,
                  answers: list[tuple[float, int]] | None = None) -> list[float]:
    """Latencies of /healthz probes sent on a fixed schedule until `stop` is set; `answers`, when
    given, receives (time.perf_counter() when answered, status code) of each probe."""
    async def run() -> list[float]:
        latencies: list[float] = []
        async with httpx.AsyncClient(base_url=base, timeout=60) as http:
            async def one(due: float) -> None:
                response = await http.get("/healthz")
                latencies.append(time.perf_counter() - due)
                if answers is not None:
                    answers.append((time.perf_counter(), response.status_code))

            tasks, due = [], time.perf_counter()
            while not stop.is_set():
                tasks.append(asyncio.create_task(one(due)))
                due += every
                await asyncio.sleep(max(0.0, due - time.perf_counter()))
            await asyncio.gather(*tasks)
        return latencies

    return asyncio.run(run())
