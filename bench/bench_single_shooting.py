"""Single shooting's solve against a peer source tree (e.g. the commit before a change), interleaved.

    git worktree add /tmp/greyfit-base <commit>      # the peer: the code to compare with
    python bench/bench_single_shooting.py --peer /tmp/greyfit-base [--rounds 15] [--cases 101 seat 40000]

Two worker processes, one per source tree (the peer's imported from its folders ahead of the
installed one), each with its own compile cache, fit the same requests: 2 states × 101 samples,
seed 000's seat model (8 states, 1000 samples) and 2 states × 40 000 samples, all
`single_shooting`. Each worker fits every case once first (compiles, warms), then the rounds
alternate A B A B … per case; the table gives the medians of CPU time (`time.process_time`, steadier
than wall time on a shared machine) and wall time of the whole fit and of the solver's own
CPU time in Ipopt's solves (`run_ipopt`), the iterations, the cost, and the largest relative
difference of the estimates between the two trees (the same optimum is the point). The load
average is printed before and after.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def _use_source(src: Path) -> None:
    """Import `greyfit` from `src` (folders schemas/, solvers/, service/, greyfit/) ahead of the
    installed tree: a temporary package whose subpackages are links into `src`."""
    shim = Path(tempfile.mkdtemp(prefix="greyfit-src-"))
    pkg = shim / "greyfit"
    pkg.mkdir()
    for item in (src / "greyfit").iterdir():
        (pkg / item.name).symlink_to(item)
    for sub in ("schemas", "solvers", "service"):
        (pkg / sub).symlink_to(src / sub)
    sys.path.insert(0, str(shim))


def _request(case: str):
    from greyfit.schemas import FitRequest
    from tests.systems import msd_experiment, msd_model, seat_experiment, seat_model, simulate_msd, simulate_seat
    if case == "seat":
        from bench.bench_methods import start_guess
        t, x, _dx, w, wd = simulate_seat(seed=0)
        exp = seat_experiment(t, x, w, wd, noise=0.01, seed=3)
        return FitRequest.model_validate({"model": seat_model(start_guess()), "experiments": [exp],
                                          "method": "single_shooting", "options": {"substeps": 2}})
    n = int(case)
    t = np.arange(n) * 0.01
    model = msd_model()
    model["outputs"] = {"x": "x"}
    exp = msd_experiment(t, simulate_msd(t), noise=0.01, seed=1, outputs=("x",))
    return FitRequest.model_validate({"model": model, "experiments": [exp], "method": "single_shooting"})


def worker(src: str) -> None:
    """Fit the case named on each stdin line; answer one JSON line."""
    _use_source(Path(src))
    sys.path.insert(1, str(ROOT))
    from greyfit.solvers.fit import fit_model
    from greyfit.solvers.nlp import solver as nlp_solver
    solve_cpu = []
    run_ipopt = nlp_solver.run_ipopt

    def timed_ipopt(*args, **kwargs):   # the solve's own CPU time (the structured path calls this)
        c0 = time.process_time()
        try:
            return run_ipopt(*args, **kwargs)
        finally:
            solve_cpu.append(time.process_time() - c0)

    nlp_solver.run_ipopt = timed_ipopt
    requests: dict = {}
    for line in sys.stdin:
        case = line.strip()
        if not case:
            continue
        req = requests.get(case) or requests.setdefault(case, _request(case))
        solve_cpu.clear()
        c0, w0 = time.process_time(), time.perf_counter()
        res = fit_model(req)
        cpu, wall = time.process_time() - c0, time.perf_counter() - w0
        print(json.dumps({"cpu": cpu, "wall": wall, "solve": sum(solve_cpu),
                          "iterations": res.solver.iterations, "compiled": res.solver.compiled,
                          "cost": res.metrics.cost, "params": {k: p.value for k, p in res.parameters.items()}}),
              flush=True)


class _Worker:
    def __init__(self, src: Path, cache: str):
        env = dict(os.environ, GREYFIT_CACHE_DIR=cache, OPENBLAS_NUM_THREADS="1", GREYFIT_COMPILE="always")
        self.proc = subprocess.Popen([sys.executable, __file__, "--worker", str(src)], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True, env=env, cwd=str(ROOT))

    def fit(self, case: str) -> dict:
        assert self.proc.stdin is not None and self.proc.stdout is not None
        self.proc.stdin.write(case + "\n")
        self.proc.stdin.flush()
        line = self.proc.stdout.readline()
        if not line:
            raise RuntimeError(f"worker {self.proc.args} ended")
        return json.loads(line)

    def close(self) -> None:
        if self.proc.stdin is not None:
            self.proc.stdin.close()
        self.proc.wait(timeout=60)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    parser.add_argument("--peer", type=Path, required=False, help="source tree to compare with")
    parser.add_argument("--rounds", type=int, default=15)
    parser.add_argument("--cases", nargs="*", default=["101", "seat", "40000"])
    args = parser.parse_args()
    if args.worker:
        worker(args.worker)
        return
    if args.peer is None:
        parser.error("--peer is required")
    print(f"load average before: {os.getloadavg()}")
    trees = {"this": ROOT, "peer": args.peer.resolve()}
    with tempfile.TemporaryDirectory() as cache:
        workers = {name: _Worker(src, os.path.join(cache, name)) for name, src in trees.items()}
        results: dict = {(name, case): [] for name in trees for case in args.cases}
        for case in args.cases:
            for w in workers.values():
                w.fit(case)   # compile and warm
            rounds = args.rounds if case != "40000" else max(3, args.rounds // 3)
            for r in range(rounds):
                order = list(workers.items()) if r % 2 == 0 else list(workers.items())[::-1]
                for name, w in order:
                    results[(name, case)].append(w.fit(case))
        for w in workers.values():
            w.close()
    print(f"load average after:  {os.getloadavg()}")
    print(f"{'case':10s} {'tree':5s} {'cpu ms':>8s} {'wall ms':>8s} {'solve cpu':>9s} {'iter':>4s} {'C':>5s} "
          f"{'cost':>14s} {'max rel diff':>12s}")
    for case in args.cases:
        med = {}
        for name in trees:
            rows = results[(name, case)]
            med[name] = {k: 1e3 * float(np.median([r[k] for r in rows])) for k in ("cpu", "wall", "solve")}
            last = rows[-1]
            pa, pb = results[("this", case)][-1]["params"], results[("peer", case)][-1]["params"]
            diff = max(abs(pa[k] - pb[k]) / max(abs(pb[k]), 1e-300) for k in pb)
            print(f"{case:10s} {name:5s} {med[name]['cpu']:8.2f} {med[name]['wall']:8.2f} {med[name]['solve']:9.2f} "
                  f"{last['iterations']:4d} {str(last['compiled']):>5s} {last['cost']:14.8e} {diff:12.2e}")
        print(f"{'':10s} ratio this/peer: cpu {med['this']['cpu'] / med['peer']['cpu']:.2f}, "
              f"solve {med['this']['solve'] / med['peer']['solve']:.2f}")


if __name__ == "__main__":
    main()
