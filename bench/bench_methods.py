"""Benchmark: seed 000's seat model (8 damping/stiffness values) with each greyfit method against
the obvious peer, scipy `least_squares` + `solve_ivp` single shooting, from the same start.

Prints one table: wall time, worst relative parameter error, iterations and the peak resident
memory of each fit (each fit runs in a fresh process, so the peak is its own).

    python bench/bench_methods.py [--noise 0.01] [--skip-scipy]
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import resource
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.systems import SEAT_TRUTH, seat_experiment, seat_model, seat_rhs, simulate_seat  # noqa: E402

NAMES = list(SEAT_TRUTH)


def start_guess() -> dict:
    return {k: v * (1.4 if i % 2 else 0.6) for i, (k, v) in enumerate(SEAT_TRUTH.items())}


def run_greyfit(method: str, noise: float, queue) -> None:
    from greyfit.schemas import FitRequest
    from greyfit.solvers.fit import fit_model
    t, x, dx, w, wd = simulate_seat(seed=0)
    # equation error on seed 000's own setting: measured q, q', q'' without noise
    exp = seat_experiment(t, x, w, wd, dx=dx if method == "equation_error" else None,
                          noise=0.0 if method == "equation_error" else noise, seed=3)
    if method == "equation_error_sg":
        method = "equation_error"   # noisy states, derivatives estimated by Savitzky-Golay
    req = FitRequest.model_validate({"model": seat_model(start_guess()), "experiments": [exp],
                                     "method": method, "options": {"substeps": 2}})
    start = time.perf_counter()
    res = fit_model(req)
    wall = time.perf_counter() - start
    start = time.perf_counter()
    fit_model(req)     # a second fit in the same process: what a warm service worker sees
    warm = time.perf_counter() - start
    est = {k: res.parameters[k].value for k in NAMES}
    queue.put((wall, warm, est, res.solver.iterations, res.success,
               resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024))


def run_scipy(noise: float, queue) -> None:
    from scipy.integrate import solve_ivp
    from scipy.optimize import least_squares
    t, x, dx, w, wd = simulate_seat(seed=0)
    exp = seat_experiment(t, x, w, wd, noise=noise, seed=3)
    y = np.array([exp["outputs"][s] for s in ["q1", "q2", "q3", "q4", "v1", "v2", "v3", "v4"]])
    scale = np.array(list(SEAT_TRUTH.values()))
    wf = lambda tt: np.interp(tt, t, w)    # noqa: E731 (same first-order hold as greyfit)
    wdf = lambda tt: np.interp(tt, t, wd)  # noqa: E731
    sd = y.std(axis=1, keepdims=True)

    def residual(theta):
        p = dict(zip(NAMES, theta * scale))
        sol = solve_ivp(lambda tt, s: seat_rhs(tt, s, p, wf, wdf), (0, t[-1]), y[:, 0], t_eval=t,
                        method="RK45", rtol=1e-8, atol=1e-10)
        if not sol.success or sol.y.shape[1] != t.size:
            return np.full(y.size, 1e3)
        return ((sol.y - y) / sd).ravel()

    theta0 = np.array([start_guess()[k] for k in NAMES]) / scale
    start = time.perf_counter()
    sol = least_squares(residual, theta0, bounds=(0, np.inf), method="trf", diff_step=1e-4,
                        x_scale=1.0, max_nfev=300)
    wall = time.perf_counter() - start
    queue.put((wall, float("nan"), dict(zip(NAMES, sol.x * scale)), sol.nfev, bool(sol.success),
               resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024))


def in_fresh_process(target, *args):
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    proc = ctx.Process(target=target, args=(*args, queue))
    proc.start()
    out = queue.get()
    proc.join()
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--noise", type=float, default=0.01, help="state noise, relative to each RMS")
    parser.add_argument("--skip-scipy", action="store_true")
    args = parser.parse_args()
    rows = []
    for method in ["equation_error", "equation_error_sg", "single_shooting", "multiple_shooting"]:
        rows.append((f"greyfit {method}", *in_fresh_process(run_greyfit, method, args.noise)))
    if not args.skip_scipy:
        rows.append(("scipy least_squares+solve_ivp", *in_fresh_process(run_scipy, args.noise)))
    print(f"seat model (seed 000), 1000 samples, 8 states, noise {args.noise:.0%} of RMS, start ±40 %")
    print("(equation_error: noise-free q, q', q'' as in seed 000; equation_error_sg: noisy states, derivatives"
          " by Savitzky-Golay)")
    print(f"{'method':34s} {'wall [s]':>9s} {'warm [s]':>9s} {'max rel err':>12s} {'iter/nfev':>10s} "
          f"{'ok':>4s} {'peak MB':>8s}")
    peer = rows[-1][1] if not args.skip_scipy else None   # wall time of the scipy fit
    for name, wall, warm, est, iters, ok, mem in rows:
        err = max(abs(est[k] / SEAT_TRUTH[k] - 1) for k in NAMES)
        speed = f"  ({peer / wall:5.1f}x faster than scipy)" if peer and not name.startswith("scipy") else ""
        print(f"{name:34s} {wall:9.3f} {warm:9.3f} {err:12.2e} {iters:10d} {str(ok):>4s} {mem:8.0f}{speed}")
    print("noise biases equation error (seed 004): use it for a start or on clean data, output error for the answer")


if __name__ == "__main__":
    main()
