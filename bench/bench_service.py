"""Benchmark the HTTP service on loopback: synchronous fit latency and batch throughput.

Starts a real `greyfit serve` for each configuration, then prints one table:
- latency of a small synchronous fit (mass-spring-damper, 101 samples), p50/p95 over 200 requests;
- throughput of a batch job of 100 such fits (401 samples) with 1 and with 2 worker processes
  (target >= 1.8x), from just before POST /v1/jobs until the job's `finished_at` (the server's
  clock, the same machine's): polls every 0.25 s find the job finished without adding their
  interval to the time or much of their own work to the server's.

Measured on a warm server: every worker has run one fit of the same shape first (a worker's first
fit builds or loads its compiled functions, a second or more), the batch one as a job task, and
the clock starts once no compiled library is being built in the background. Request bodies are made
and encoded before the clock starts: the client's own JSON encoding is not the server's time. Beside wall time,
the CPU seconds of the server process and of its worker processes per fit (from /proc), which
show whether a slow run was this server's work or a busy machine, and the part of the mean latency
spent outside the worker's task (parsing the request, fitting, the result's JSON; its own clock, from
/metrics): HTTP, the server and the hand-over to the worker and back.

    python bench/bench_service.py [--requests 200] [--batch 100] [--repeat 3] [--latency-only]

`--latency-only` measures the synchronous latency alone, `--repeat` times (a fresh server each),
and prints the median of each row: the quick loop for work on the request path.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.servers import free_port, unix_time  # noqa: E402
from tests.servers import stop_server as stop  # noqa: E402
from tests.systems import msd_experiment, msd_model, simulate_msd  # noqa: E402

JSON = {"content-type": "application/json"}
POLL_SECONDS = 0.25


def msd_bodies(count: int, n: int) -> list[dict]:
    """tests.service.conftest.msd_request(seed, n=n) for seeds 0..count-1, simulated once."""
    t = np.linspace(0, 10, n)
    states = simulate_msd(t)
    return [{"model": msd_model(c=0.5, k=3.0), "method": "multiple_shooting",
             "experiments": [msd_experiment(t, states, noise=0.005, seed=seed)]} for seed in range(count)]


def serve(workers: int, data_dir: str, port: int) -> subprocess.Popen:
    proc = subprocess.Popen([sys.executable, "-m", "greyfit.service.cli", "serve", "--port", str(port),
                             "--data-dir", data_dir, "--workers", str(workers)], cwd=ROOT,
                            start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                            )
    for _ in range(300):
        try:
            if httpx.get(f"http://127.0.0.1:{port}/readyz", timeout=1).status_code == 200:
                return proc
        except httpx.HTTPError:
            time.sleep(0.1)
    raise RuntimeError("server did not start")


def cpu_seconds(pid: int) -> float:
    """User + system CPU of a process (0 where /proc is missing)."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def children(pid: int) -> list[int]:
    try:
        return [int(p) for p in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        return []


class CpuMeter:
    """CPU seconds the server process and its children spent between start() and stop()."""

    def __init__(self, pid: int):
        self.pid = pid

    def start(self) -> None:
        self.kids = children(self.pid)
        self.before = [cpu_seconds(p) for p in [self.pid, *self.kids]]

    def stop(self) -> tuple[float, float]:
        after = [cpu_seconds(p) for p in [self.pid, *self.kids]]
        spent = [a - b for a, b in zip(after, self.before)]
        return spent[0], sum(spent[1:])


def warm(client: httpx.Client, body: bytes, workers: int) -> None:
    """One synchronous fit on each worker: as many at once as there are workers."""
    threads = [threading.Thread(target=client.post, args=("/v1/fits",), kwargs={"content": body, "headers": JSON})
               for _ in range(workers)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()


def wait_for_builds(client: httpx.Client, body: bytes, data_dir: str, workers: int, timeout: float = 180) -> None:
    """Warm fits until every worker answers from compiled code and no library is being built.

    A worker's first fits of a model run interpreted while gcc builds its libraries in the background
    (about a second of CPU each, on the cores the measured fits need); each build works in a
    temporary directory inside the cache until its library is renamed into place."""
    compiled = Path(data_dir) / "cache" / "compiled"
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        building = compiled.is_dir() and any(p.is_dir() for p in compiled.iterdir())
        answers = [client.post("/v1/fits", content=body, headers=JSON).json() for _ in range(2 * workers)]
        if not building and all(a.get("solver", {}).get("compiled") is not False for a in answers):
            return
        time.sleep(0.2)
    raise RuntimeError(f"compiled libraries still building after {timeout} s")


def fit_seconds(client: httpx.Client) -> float:
    """The workers' own wall time of all fits so far (parse, fit, result JSON), from /metrics."""
    for line in client.get("/metrics").text.splitlines():
        if line.startswith('greyfit_fit_duration_seconds_sum{kind="fit"}'):
            return float(line.split()[-1])
    return 0.0


def latency(n: int) -> tuple[float, float, float, float, float, float]:
    port = free_port()
    bodies = [json.dumps(b).encode() for b in msd_bodies(n, 101)]
    with tempfile.TemporaryDirectory() as tmp:
        proc = serve(2, tmp, port)
        try:
            with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=60) as client:
                for _ in range(3):
                    warm(client, bodies[0], 2)
                wait_for_builds(client, bodies[0], tmp, 2)
                in_workers = fit_seconds(client)
                meter = CpuMeter(proc.pid)
                meter.start()
                times = []
                for body in bodies:
                    t0 = time.perf_counter()
                    resp = client.post("/v1/fits", content=body, headers=JSON)
                    times.append(time.perf_counter() - t0)
                    assert resp.status_code == 200, resp.text
                server_cpu, worker_cpu = meter.stop()
                in_workers = fit_seconds(client) - in_workers
        finally:
            stop(proc)
    ms = np.array(times) * 1000
    return (float(np.percentile(ms, 50)), float(np.percentile(ms, 95)), float(ms.mean()),
            1000 * server_cpu / n, 1000 * worker_cpu / n, float(ms.mean()) - 1000 * in_workers / n)


def throughput(workers: int, n: int, body: bytes) -> tuple[float, float, float]:
    port = free_port()
    with tempfile.TemporaryDirectory() as tmp:
        proc = serve(workers, tmp, port)
        try:
            with httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=60) as client:
                # a job of one task per worker (each free worker takes one): warms the workers and
                # the job routes (FastAPI builds a router's routes on its first request)
                first = json.loads(body)["requests"][0]
                job_id = client.post("/v1/jobs", json={"requests": [first] * workers}).json()["id"]
                while client.get(f"/v1/jobs/{job_id}").json()["status"] in ("queued", "running"):
                    time.sleep(POLL_SECONDS)
                wait_for_builds(client, json.dumps(first).encode(), tmp, workers)
                meter = CpuMeter(proc.pid)
                meter.start()
                t0 = time.time()
                job_id = client.post("/v1/jobs", content=body, headers=JSON).json()["id"]
                while (job := client.get(f"/v1/jobs/{job_id}").json())["status"] in ("queued", "running"):
                    time.sleep(POLL_SECONDS)
                server_cpu, worker_cpu = meter.stop()
                elapsed = unix_time(job["finished_at"]) - t0
                assert job["progress"]["succeeded"] == n, job["progress"]
        finally:
            stop(proc)
    return n / elapsed, 1000 * server_cpu / n, 1000 * worker_cpu / n


def print_latency(p50: float, p95: float, mean: float, server_cpu: float, worker_cpu: float,
                  outside: float) -> None:
    print(f"{'sync fit latency p50 (msd, 101 samples)':48s} {p50:10.1f} ms")
    print(f"{'sync fit latency p95':48s} {p95:10.1f} ms")
    print(f"{'sync fit latency mean':48s} {mean:10.1f} ms")
    print(f"{'  of which outside the fit task (mean)':48s} {outside:10.1f} ms")
    print(f"{'  CPU per sync fit: server / workers':48s} {server_cpu:5.1f} / {worker_cpu:4.1f} ms")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--requests", type=int, default=200)
    parser.add_argument("--batch", type=int, default=100)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--latency-only", action="store_true",
                        help="only the synchronous latency, --repeat servers, medians")
    args = parser.parse_args()
    if args.latency_only:
        rows = []
        for _ in range(args.repeat):
            rows.append(latency(args.requests))
            p50, p95, mean, s_cpu, w_cpu, outside = rows[-1]
            print(f"  p50 {p50:5.1f} ms, p95 {p95:5.1f} ms, mean {mean:5.1f} ms, outside the worker's task "
                  f"{outside:4.1f} ms  (CPU per fit: server {s_cpu:4.1f} ms, workers {w_cpu:4.1f} ms)", flush=True)
        print(f"greyfit service on loopback ({os.cpu_count()} cores), sync latency, median of {args.repeat}")
        print(f"{'measure':48s} {'value':>12s}")
        print_latency(*(float(v) for v in np.median(np.array(rows), axis=0)))
        return
    p50, p95, mean, sync_server_cpu, sync_worker_cpu, outside = latency(args.requests)
    body = json.dumps({"requests": msd_bodies(args.batch, 401)}).encode()
    # interleaved repetitions, medians: this VM's speed drifts by ±20 % over a minute
    runs: dict[int, list] = {1: [], 2: []}
    for _ in range(args.repeat):
        for workers in (1, 2):
            runs[workers].append(throughput(workers, args.batch, body))
            rate, s_cpu, w_cpu = runs[workers][-1]
            print(f"  {workers} worker(s): {rate:6.2f} fits/s  (CPU per fit: server {s_cpu:5.1f} ms, "
                  f"workers {w_cpu:5.1f} ms)", flush=True)
    med = {w: np.median(np.array(r), axis=0) for w, r in runs.items()}
    t1, t2 = float(med[1][0]), float(med[2][0])
    print(f"greyfit service on loopback ({os.cpu_count()} cores)")
    print(f"{'measure':48s} {'value':>12s}")
    print_latency(p50, p95, mean, sync_server_cpu, sync_worker_cpu, outside)
    print(f"{f'batch of {args.batch} fits (401 samples), 1 worker':48s} {t1:8.2f} fits/s  (median of {args.repeat})")
    print(f"{f'batch of {args.batch} fits (401 samples), 2 workers':48s} {t2:8.2f} fits/s  (median of {args.repeat})")
    for w in (1, 2):
        print(f"{f'  CPU per batch fit, {w} worker(s): server / workers':48s} {med[w][1]:5.1f} / {med[w][2]:4.1f} ms")
    print(f"{'speed-up 2 vs 1 worker (target >= 1.8x)':48s} {t2 / t1:10.2f} x")
    # back-to-back runs share the machine's speed of that minute, which drifts by ±20 % here
    pairs = [two[0] / one[0] for one, two in zip(runs[1], runs[2])]
    print(f"{'  per back-to-back pair of runs':48s} " + ", ".join(f"{r:.2f}" for r in pairs) + " x")
    print(f"{'  workers CPU per fit, 2 vs 1 worker':48s} {med[2][2] / med[1][2]:10.2f} x")


if __name__ == "__main__":
    main()
