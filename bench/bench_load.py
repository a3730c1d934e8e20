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
    python bench/bench_load.py --bodies [--rounds 3] [--parser-processes 1 0]

`--bodies` measures instead what tests/service/test_real_server_bodies.py only checks for
correctness: with no other load, three 20 MB fit bodies arrive at once (each parsed in full, then
refused by the server's sample limit), /healthz probed in open loop meanwhile; it prints the probes'
p50/p95/max and, for scale, one parse and validation of such a body in this process (parsed in the
web process the burst stalled the probes for about four parses: p95 934 ms with one parse 214 ms;
in a parser process the probes waited only for their share of the CPU: p95 ~30 ms quiet, 337 ms at
load 3.6 with one parse at 334 ms).

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

from greyfit.schemas import FitRequest  # noqa: E402
from greyfit.service.http.json_parsing import parse_and_validate  # noqa: E402
from tests.servers import free_port, large_fit_request, msd_request, probe_healthz, start_server, stop_server  # noqa: E402

BODIES_MEGABYTES = 20


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


def parse_seconds(body: bytes) -> float:
    """Wall time of one parse and validation of `body` in this process, as a parser process does it."""
    started = time.perf_counter()
    outcome, _ = parse_and_validate(FitRequest, body)
    assert outcome == "ok", outcome
    return time.perf_counter() - started


def run_bodies_row(base: str, body: bytes) -> dict:
    """/healthz probed in open loop while three copies of `body` are posted at once."""
    stop = threading.Event()
    health: list[float] = []
    statuses: collections.Counter = collections.Counter()
    prober = threading.Thread(target=lambda: health.extend(probe_healthz(base, stop)))
    prober.start()

    def post(_: int) -> None:
        resp = httpx.post(f"{base}/v1/fits", content=body, timeout=120, headers={"content-type": "application/json"})
        statuses[resp.status_code] += 1

    posts = [threading.Thread(target=post, args=(i,)) for i in range(3)]
    time.sleep(0.2)
    for t in posts:
        t.start()
    for t in posts:
        t.join()
    stop.set()
    prober.join()
    return {"p50": np.percentile(health, 50) * 1e3, "p95": np.percentile(health, 95) * 1e3,
            "max": max(health) * 1e3, "probes": len(health), "statuses": dict(statuses)}


def bodies_main(args: argparse.Namespace) -> None:
    """The --bodies rows: three 20 MB bodies at once, per parser setting, `args.rounds` fresh servers."""
    fit = large_fit_request(BODIES_MEGABYTES)
    n = len(fit["experiments"][0]["time"])
    body = json.dumps(fit).encode()
    print(f"{'parser':>6s} {'round':>5s} {'healthz p50':>11s} {'p95 ms':>7s} {'max ms':>7s} {'probes':>6s} "
          f"{'one parse ms':>12s} {'load avg':>8s}  answers")
    for processes in args.parser_processes:
        for k in range(args.rounds):
            port = free_port()
            with tempfile.TemporaryDirectory() as tmp:
                server = start_server(Path(tmp), port, workers=1, GREYFIT_MAX_SAMPLES_PER_EXPERIMENT=str(n - 1),
                                      GREYFIT_BODY_PARSER_PROCESSES=str(processes))
                try:
                    one = parse_seconds(body)
                    row = run_bodies_row(f"http://127.0.0.1:{port}", body)
                    one = (one + parse_seconds(body)) / 2
                finally:
                    stop_server(server)
            where = f"{processes} proc" if processes else "thread"
            print(f"{where:>6s} {k:5d} {row['p50']:11.0f} {row['p95']:7.0f} {row['max']:7.0f} {row['probes']:6d} "
                  f"{one * 1e3:12.0f} {os.getloadavg()[0]:8.1f}  {row['statuses']}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=15.0)
    parser.add_argument("--clients", type=int, nargs="+", default=[20, 50])
    parser.add_argument("--parser-processes", type=int, nargs="+", default=[1, 0],
                        help="GREYFIT_BODY_PARSER_PROCESSES of each server (0: parse in a thread)")
    parser.add_argument("--bodies", action="store_true",
                        help="three 20 MB bodies at once and nothing else (the test_real_server_bodies scenario)")
    parser.add_argument("--rounds", type=int, default=3, help="--bodies: fresh servers per parser setting")
    args = parser.parse_args()
    if args.bodies:
        bodies_main(args)
        return
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
