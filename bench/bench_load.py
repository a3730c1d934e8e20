"""Load test of the HTTP service on loopback: many concurrent clients of synchronous fits.

Starts a real `greyfit serve` (2 workers) and, for 20 and 50 concurrent clients, each client posts
small synchronous fits (mass-spring-damper, 101 samples) for a fixed time; optionally, meanwhile, a
burst of large bodies (8 at once, 40 MB each: each fits GREYFIT_MAX_BODY_BYTES, together they
exceed the in-flight budget) arrives. Prints one table: throughput, latency p50/p95/p99 of the
fits, answers by status, the peak resident memory of the server with its workers, and /healthz
probed in open loop (every 25 ms, each probe timed from when it was due: a stall counts in every
probe it delays). The peer in the same run: the same server parsing large bodies in a thread of the
web process (GREYFIT_BODY_PARSER_PROCESSES=0, what it did before) instead of a parser process.

    python bench/bench_load.py [--seconds 15] [--clients 20 50] [--parser-processes 1 0]

Bounded: loopback only, a fixed duration per row, every client stops by itself.
"""
from __future__ import annotations

import argparse
import collections
import json
import os
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.servers import free_port, large_fit_request, msd_request, probe_healthz, start_server, stop_server  # noqa: E402


def tree_rss_mb(pid: int) -> float:
    """Resident memory of a process and its children (the workers), from /proc."""
    total, todo = 0, [pid]
    while todo:
        p = todo.pop()
        try:
            with open(f"/proc/{p}/statm") as f:
                total += int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
            with open(f"/proc/{p}/task/{p}/children") as f:
                todo += [int(c) for c in f.read().split()]
        except (FileNotFoundError, ProcessLookupError):
            continue
    return total / 2 ** 20


def large_body(megabytes: int) -> bytes:
    """A fit request whose time series make the body about this large (refused as too big for sync)."""
    return json.dumps(large_fit_request(megabytes)).encode()


def run_row(base: str, pid: int, clients: int, seconds: float, burst: bytes | None) -> dict:
    bodies = [json.dumps(msd_request(i)).encode() for i in range(20)]
    latencies: list[float] = []
    statuses: collections.Counter = collections.Counter()
    burst_statuses: collections.Counter = collections.Counter()
    lock, stop = threading.Lock(), time.monotonic() + seconds
    peak = [tree_rss_mb(pid)]
    health: list[float] = []
    probes_done = threading.Event()

    def client(i: int) -> None:
        with httpx.Client(base_url=base, timeout=120) as http:
            k = i
            while time.monotonic() < stop:
                t0 = time.perf_counter()
                resp = http.post("/v1/fits", content=bodies[k % len(bodies)],
                                 headers={"content-type": "application/json"})
                with lock:
                    statuses[resp.status_code] += 1
                    if resp.status_code == 200:
                        latencies.append(time.perf_counter() - t0)
                if resp.status_code == 503:
                    time.sleep(float(resp.headers.get("retry-after", 1)))
                k += 1

    def big(_: int) -> None:
        with httpx.Client(base_url=base, timeout=120) as http:
            resp = http.post("/v1/fits", content=burst, headers={"content-type": "application/json"})
            with lock:
                burst_statuses[resp.status_code] += 1

    def sample() -> None:
        while time.monotonic() < stop + 1:
            peak[0] = max(peak[0], tree_rss_mb(pid))
            time.sleep(0.1)
        probes_done.set()

    threads = [threading.Thread(target=client, args=(i,)) for i in range(clients)]
    threads.append(threading.Thread(target=sample))
    threads.append(threading.Thread(target=lambda: health.extend(probe_healthz(base, probes_done))))
    if burst is not None:
        threads += [threading.Thread(target=big, args=(i,)) for i in range(8)]
    started = time.monotonic()
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    wall = time.monotonic() - started
    lat = np.array(latencies) * 1e3 if latencies else np.array([np.nan])
    return {"clients": clients, "burst": burst is not None, "fits_per_s": len(latencies) / wall,
            "p50": np.percentile(lat, 50), "p95": np.percentile(lat, 95), "p99": np.percentile(lat, 99),
            "statuses": dict(statuses), "burst_statuses": dict(burst_statuses), "peak_mb": peak[0],
            "healthz_p95_ms": np.percentile(health, 95) * 1e3 if health else float("nan"),
            "healthz_max_ms": max(health) * 1e3 if health else float("nan")}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=15.0)
    parser.add_argument("--clients", type=int, nargs="+", default=[20, 50])
    parser.add_argument("--parser-processes", type=int, nargs="+", default=[1, 0],
                        help="GREYFIT_BODY_PARSER_PROCESSES of each server (0: parse in a thread)")
    args = parser.parse_args()
    burst = large_body(40)
    rows = []
    for processes in args.parser_processes:
        port = free_port()
        with tempfile.TemporaryDirectory() as tmp:
            server = start_server(Path(tmp), port, workers=2, GREYFIT_POLL_SECONDS="0.05",
                                  GREYFIT_BODY_PARSER_PROCESSES=str(processes))
            base = f"http://127.0.0.1:{port}"
            try:
                for body in (json.dumps(msd_request(0)).encode(),) * 4:   # warm the workers
                    httpx.post(f"{base}/v1/fits", content=body, headers={"content-type": "application/json"},
                               timeout=60)
                rows += [{"parser": processes, **run_row(base, server.pid, c, args.seconds, b)}
                         for c in args.clients for b in (None, burst)]
            finally:
                stop_server(server)
    print(f"{'parser':>6s} {'clients':>7s} {'40 MB burst':>11s} {'fits/s':>7s} {'p50 ms':>8s} {'p95 ms':>8s} "
          f"{'p99 ms':>8s} {'peak MB':>8s} {'healthz p95':>11s} {'max ms':>7s}  answers (burst answers)")
    for r in rows:
        where = f"{r['parser']} proc" if r["parser"] else "thread"
        print(f"{where:>6s} {r['clients']:7d} {('yes' if r['burst'] else 'no'):>11s} {r['fits_per_s']:7.1f} "
              f"{r['p50']:8.0f} {r['p95']:8.0f} {r['p99']:8.0f} {r['peak_mb']:8.0f} {r['healthz_p95_ms']:11.0f} "
              f"{r['healthz_max_ms']:7.0f}  {r['statuses']} {r['burst_statuses'] or ''}")
    print("(2-core machine shared with other work: timings are noisy, ±30 % or worse)")


if __name__ == "__main__":
    main()
