"""Batches and cold start: 200 small fits through the jobs API and `greyfit batch`, beside one Python
loop of `greyfit.fit`; and the seat model's first fit in a fresh process beside its warm-interpreted fit.

    python bench/bench_batch.py [--fits 200] [--rounds 3] [--workers 2] [--skip-seat] [--skip-batch]

Batch rows (the mass-spring-damper of bench_service.py, 401 samples, `multiple_shooting`):
- jobs API: a real `greyfit serve --workers W`, warmed (each worker has fitted the structure and no
  library is being built), from just before POST /v1/jobs to the job's `finished_at`; CPU of the
  server and its workers (from /proc);
- `greyfit batch --workers W`: the whole command in a fresh process (start, imports, workers, fits,
  results written), its compiled-kernel cache on disk already filled by a first run; CPU of the
  command and its workers (getrusage of the reaped children);
- one loop: `greyfit.fit` over the same requests in one process, after one fit of the structure
  (its own clocks, around the loop only).
The three run interleaved, in a rotating order each round; the table shows medians over the rounds
and the load average before each.

Seat rows (seed 000's seat model, 1 000 samples, 8 states, the default method): a fresh process with
an empty cache runs its first fit (`GREYFIT_COMPILE` unset: gcc may run beside it); another fresh
process with `GREYFIT_COMPILE=never` runs it 1 + 3 times, its median warm fit the reference. The two
alternate for `--rounds` rounds. The target (issue #26): the first fit within 1.5x the warm-interpreted one.
CPU time is the steadier number on a shared machine (gcc's own CPU is the child's, not counted).
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.bench_service import POLL_SECONDS, CpuMeter, msd_bodies, serve, wait_for_builds  # noqa: E402
from tests.servers import free_port, unix_time  # noqa: E402
from tests.servers import stop_server as stop  # noqa: E402

JSON = {"content-type": "application/json"}
LOOP = """
import json, sys, time
import greyfit
texts = open(sys.argv[1]).read().splitlines()
reqs = [greyfit.FitRequest.model_validate_json(t) for t in texts]
greyfit.fit(reqs[0])
c0, w0 = time.process_time(), time.perf_counter()
ok = sum(greyfit.fit(r).success for r in reqs)
print(json.dumps([time.perf_counter() - w0, time.process_time() - c0, ok]))
"""
SEAT = """
import json, sys, time
sys.path.insert(0, sys.argv[1])
from bench.bench_methods import start_guess
from tests.systems import SEAT_TRUTH, seat_experiment, seat_model, simulate_seat
t, x, dx, w, wd = simulate_seat(seed=0)
body = {"model": seat_model(start_guess()), "experiments": [seat_experiment(t, x, w, wd, noise=0.01, seed=3)]}
import greyfit
req = greyfit.FitRequest.model_validate(body)
rows = []
for _ in range(int(sys.argv[2])):
    c0, w0 = time.process_time(), time.perf_counter()
    res = greyfit.fit(req)
    err = max(abs(res.parameters[k].value / v - 1) for k, v in SEAT_TRUTH.items())
    rows.append([time.perf_counter() - w0, time.process_time() - c0, res.solver.compiled, err,
                 res.solver.iterations, res.solver.method.value])
print(json.dumps(rows))
"""


def child_env(**extra: str) -> dict:
    return {**os.environ, "OPENBLAS_NUM_THREADS": "1", "PYTHONPATH": str(ROOT), **extra}


def run_child(args: list[str], env: dict) -> tuple[float, float, str]:
    """(wall, CPU of the process and everything it reaped, stdout) of one command."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    w0 = time.perf_counter()
    out = subprocess.run(args, env=env, cwd=ROOT, capture_output=True, text=True, check=True).stdout
    wall = time.perf_counter() - w0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime), out


class JobsApi:
    """One warm server for all rounds: each round posts one job of every request."""

    def __init__(self, workers: int, bodies: list[dict], tmp: str):
        self.port, self.n = free_port(), len(bodies)
        self.body = json.dumps({"requests": bodies}).encode()
        self.proc = serve(workers, tmp, self.port)
        self.client = httpx.Client(base_url=f"http://127.0.0.1:{self.port}", timeout=120)
        self.run_job({"requests": [bodies[0]] * (2 * workers)})   # every worker meets the structure
        wait_for_builds(self.client, json.dumps(bodies[0]).encode(), tmp, workers)

    def run_job(self, payload) -> dict:
        content = payload if isinstance(payload, bytes) else json.dumps(payload).encode()
        job_id = self.client.post("/v1/jobs", content=content, headers=JSON).json()["id"]
        while (job := self.client.get(f"/v1/jobs/{job_id}").json())["status"] in ("queued", "running"):
            time.sleep(POLL_SECONDS)
        return job

    def measure(self) -> tuple[float, float]:
        meter = CpuMeter(self.proc.pid)
        meter.start()
        t0 = time.time()
        job = self.run_job(self.body)
        server_cpu, worker_cpu = meter.stop()
        if job["progress"]["succeeded"] != self.n:
            raise RuntimeError(f"jobs API: {job['progress']}")
        return unix_time(job["finished_at"]) - t0, server_cpu + worker_cpu

    def close(self) -> None:
        self.client.close()
        stop(self.proc)


def measure_cli(workers: int, requests: Path, out: Path, cache: str, n: int) -> tuple[float, float]:
    out.unlink(missing_ok=True)
    wall, cpu, _ = run_child([sys.executable, "-m", "greyfit.service.cli", "batch", str(requests), "--out",
                              str(out), "--workers", str(workers)], child_env(GREYFIT_CACHE_DIR=cache))
    lines = [json.loads(line) for line in out.read_text().splitlines()]
    if sum(line["status"] == "succeeded" for line in lines) != n:
        raise RuntimeError("greyfit batch: not every fit succeeded")
    return wall, cpu


def measure_loop(requests: Path, cache: str, n: int) -> tuple[float, float]:
    _, _, out = run_child([sys.executable, "-c", LOOP, str(requests)], child_env(GREYFIT_CACHE_DIR=cache))
    wall, cpu, ok = json.loads(out)
    if ok != n:
        raise RuntimeError(f"loop: {ok} of {n} fits succeeded")
    return wall, cpu


def batch_rows(args) -> None:
    bodies = msd_bodies(args.fits, 401)
    with tempfile.TemporaryDirectory() as tmp:
        requests = Path(tmp) / "requests.jsonl"
        requests.write_text("".join(json.dumps(b) + "\n" for b in bodies))
        cache = os.path.join(tmp, "cli-cache")
        warm = Path(tmp) / "warm.jsonl"
        warm.write_text(json.dumps(bodies[0]) + "\n")
        for _ in range(2):   # fills the CLI's disk cache: the second run finds it built
            run_child([sys.executable, "-m", "greyfit.service.cli", "batch", str(warm), "--out",
                       str(Path(tmp) / "warm-out.jsonl"), "--workers", "1"], child_env(GREYFIT_CACHE_DIR=cache))
            time.sleep(3)
        server_dir = os.path.join(tmp, "server")
        os.mkdir(server_dir)
        api = JobsApi(args.workers, bodies, server_dir)
        cases = {"jobs API": api.measure,
                 "greyfit batch": lambda: measure_cli(args.workers, requests, Path(tmp) / "out.jsonl", cache,
                                                      args.fits),
                 "one loop": lambda: measure_loop(requests, cache, args.fits)}
        results: dict[str, list[tuple[float, float]]] = {name: [] for name in cases}
        loads = []
        try:
            names = list(cases)
            for r in range(args.rounds):
                for name in names[r % 3:] + names[:r % 3]:
                    loads.append(os.getloadavg()[0])
                    results[name].append(cases[name]())
        finally:
            api.close()
    print(f"{args.fits} small fits (mass-spring-damper, 401 samples, multiple shooting); "
          f"{args.workers} workers; {args.rounds} rounds, medians; load before each: "
          + " ".join(f"{v:.1f}" for v in loads))
    print(f"{'path':16s} {'wall s':>8s} {'CPU s':>8s} {'ms/fit wall':>12s} {'ms/fit CPU':>11s}")
    for name, rows in results.items():
        wall, cpu = (float(np.median([row[i] for row in rows])) for i in (0, 1))
        print(f"{name:16s} {wall:8.2f} {cpu:8.2f} {1000 * wall / args.fits:12.1f} {1000 * cpu / args.fits:11.1f}")
    print("(jobs API: 2 s is issue #26's target; the loop runs on one core, the others on "
          f"{args.workers} workers)")


def seat_rows(args) -> None:
    first, warm, loads = [], [], []
    for _ in range(args.rounds):
        with tempfile.TemporaryDirectory() as cache:
            loads.append(os.getloadavg()[0])
            _, _, out = run_child([sys.executable, "-c", SEAT, str(ROOT), "1"], child_env(GREYFIT_CACHE_DIR=cache))
            first.append(json.loads(out)[0])
        with tempfile.TemporaryDirectory() as cache:
            loads.append(os.getloadavg()[0])
            _, _, out = run_child([sys.executable, "-c", SEAT, str(ROOT), "4"],
                                  child_env(GREYFIT_CACHE_DIR=cache, GREYFIT_COMPILE="never"))
            rows = json.loads(out)[1:]
            warm.append([float(np.median([row[i] for row in rows])) for i in (0, 1)] + rows[0][2:])
    print(f"\nseat model, 1000 samples: first fit in a fresh process (empty cache) vs warm interpreted; "
          f"{args.rounds} rounds, medians; load before each: " + " ".join(f"{v:.1f}" for v in loads))
    print(f"{'case':34s} {'wall s':>8s} {'CPU s':>8s} {'compiled':>9s} {'max rel err':>11s} {'iter':>5s}  method")
    for name, rows in (("first fit (GREYFIT_COMPILE=auto)", first), ("warm interpreted (never)", warm)):
        wall, cpu = (float(np.median([row[i] for row in rows])) for i in (0, 1))
        print(f"{name:34s} {wall:8.2f} {cpu:8.2f} {str(rows[-1][2]):>9s} {rows[-1][3]:11.1e} {rows[-1][4]:5d}  "
              f"{rows[-1][5]}")
    ratio = [f[i] / w[i] for f, w in zip(first, warm) for i in (0, 1)]
    print(f"first / warm interpreted: wall {np.median(ratio[0::2]):.2f}x, CPU {np.median(ratio[1::2]):.2f}x "
          "(target <= 1.5x)")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--fits", type=int, default=200)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--skip-seat", action="store_true")
    parser.add_argument("--skip-batch", action="store_true")
    args = parser.parse_args()
    if not args.skip_batch:
        batch_rows(args)
    if not args.skip_seat:
        seat_rows(args)


if __name__ == "__main__":
    main()
