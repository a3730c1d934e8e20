"""Benchmark: `method: auto` (the default) against `multiple_shooting` on the same requests.

Three problems: a mass-spring-damper measured in position (2 states, 101 samples and 40 000
samples) and the 4-mass seat model (8 states, 1 000 samples, 40 % off). Per problem both methods
run in one process, warmed up (compiled kernels ready), then interleaved A B A B; the table gives
the median CPU and wall time of the whole `fit_model`, of the NLP solve alone (the part the
choice changes; the checks around it are the same for both), the worst relative parameter
difference between the two answers, which method auto ran and the load average.

    python bench/bench_method_choice.py [--repeats 5] [--sizes 101 40000] [--skip-seat]
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.bench_methods import start_guess  # noqa: E402
from tests.systems import (  # noqa: E402
    msd_experiment,
    msd_model,
    seat_experiment,
    seat_model,
    simulate_msd,
    simulate_seat,
)

METHODS = ("auto", "multiple_shooting")


class SolveClock:
    """CPU and wall seconds spent in the batch fits' `solve` (the NLP), summed over a fit."""

    def __init__(self):
        from greyfit.solvers.methods import batch
        self.cpu = self.wall = 0.0
        for cls in (batch.OutputErrorFit, batch.EquationErrorFit):
            cls.solve = self._timed(cls.solve)

    def _timed(self, solve):
        def timed(fit, *args, **kwargs):
            c0, w0 = time.process_time(), time.perf_counter()
            try:
                return solve(fit, *args, **kwargs)
            finally:
                self.cpu += time.process_time() - c0
                self.wall += time.perf_counter() - w0
        return timed

    def reset(self):
        self.cpu = self.wall = 0.0


def msd_request(n: int, method: str):
    from greyfit.schemas import FitRequest
    t = np.arange(n) * 0.01
    model = msd_model()
    model["outputs"] = {"x": "x"}
    exp = msd_experiment(t, simulate_msd(t), noise=0.01, seed=1, outputs=("x",))
    return FitRequest.model_validate({"model": model, "experiments": [exp], "method": method})


def seat_request(method: str):
    from greyfit.schemas import FitRequest
    t, x, _, w, wd = simulate_seat(seed=0)
    exp = seat_experiment(t, x, w, wd, noise=0.01, seed=3)
    return FitRequest.model_validate({"model": seat_model(start_guess()), "experiments": [exp],
                                      "method": method, "options": {"substeps": 2}})


def measure(name: str, make, repeats: int, clock: SolveClock) -> list[str]:
    from greyfit.solvers.fit import fit_model
    reqs = {m: make(m) for m in METHODS}
    results = {m: fit_model(reqs[m]) for m in METHODS}   # warm-up: compile, caches
    for m in METHODS:
        fit_model(reqs[m])
    rows: dict[str, list[tuple[float, float, float, float]]] = {m: [] for m in METHODS}
    for _ in range(repeats):
        for m in METHODS:   # interleaved: A B A B
            clock.reset()
            c0, w0 = time.process_time(), time.perf_counter()
            results[m] = fit_model(reqs[m])
            rows[m].append((time.process_time() - c0, time.perf_counter() - w0, clock.cpu, clock.wall))
    a, b = results["auto"], results["multiple_shooting"]
    diff = max(abs(a.parameters[k].value / b.parameters[k].value - 1)
               for k in a.parameters if not a.parameters[k].fixed)
    med = {m: np.median(np.array(rows[m]), axis=0) * 1e3 for m in METHODS}
    ratio = med["auto"] / med["multiple_shooting"]
    out = []
    for m in METHODS:
        ran = results[m].solver.method.value
        out.append(f"{name:<18} {m:<18} {ran:<18} {med[m][0]:9.1f} {med[m][1]:9.1f} {med[m][2]:9.1f} "
                   f"{med[m][3]:9.1f} {results[m].solver.iterations:5d}  {results[m].quality}")
    out.append(f"{'':<18} {'auto / multiple':<18} {'':<18} {ratio[0]:9.2f} {ratio[1]:9.2f} {ratio[2]:9.2f} "
               f"{ratio[3]:9.2f}        max |Δθ/θ| = {diff:.1e}")
    if a.solver.method_choice is not None:
        out.append(f"{'':<18} why: {a.solver.method_choice.reason}")
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--sizes", type=int, nargs="*", default=[101, 40_000])
    parser.add_argument("--skip-seat", action="store_true")
    args = parser.parse_args()
    clock = SolveClock()
    cases = [(f"2 states × {n}", lambda m, n=n: msd_request(n, m)) for n in args.sizes]
    if not args.skip_seat:
        cases.insert(1, ("seat, 8 states", seat_request))
    print(f"load average before: {os.getloadavg()[0]:.2f} ({os.cpu_count()} cores); medians of "
          f"{args.repeats} interleaved fits, milliseconds")
    print(f"{'problem':<18} {'method':<18} {'ran':<18} {'fit CPU':>9} {'fit wall':>9} {'solve CPU':>9} "
          f"{'solve wall':>9} {'iter':>5}  quality")
    for name, make in cases:
        for line in measure(name, make, args.repeats, clock):
            print(line, flush=True)
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
