"""Speed of the fit engine: compiled per-sample functions, the structured multiple-shooting NLP,
long records, equation error — each against the obvious peer in the same run.

    python bench/bench_speed.py [--skip-scipy] [--sizes 4000 10000 40000]

Every row runs in a fresh process (its peak memory is its own) with an empty compile cache, so
"cold" includes generating and compiling C; "warm" is the median of three or more fits of the same
model structure in that process (up to 30 while they take less than a second in all), what a service worker sees from
its second request on. Times are wall clock on a
quiet machine; CPU time is printed beside them because this machine is often shared.

Peers: greyfit's generic CasADi graph (what multiple shooting was before the structured NLP,
`GREYFIT_STRUCTURED_SHOOTING=0`), the interpreted structured NLP (`GREYFIT_COMPILE=never`), and
scipy `least_squares` + `solve_ivp` for the seat model (bench_methods.py's peer).
"""
from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import resource
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.bench_methods import in_fresh_process, run_scipy, start_guess  # noqa: E402
from tests.systems import (  # noqa: E402
    MSD_TRUTH,
    SEAT_TRUTH,
    msd_experiment,
    msd_model,
    seat_experiment,
    seat_model,
    simulate_msd,
    simulate_seat,
)


def _timed(fit, req):
    c0, w0 = time.process_time(), time.perf_counter()
    res = fit(req)
    return time.perf_counter() - w0, time.process_time() - c0, res


def seat_request(method: str):
    from greyfit.schemas import FitRequest
    t, x, dx, w, wd = simulate_seat(seed=0)
    if method == "equation_error":   # seed 000's own setting: noise-free q, q', q''
        exp = seat_experiment(t, x, w, wd, dx=dx)
    else:
        exp = seat_experiment(t, x, w, wd, noise=0.01, seed=3)
    return FitRequest.model_validate({"model": seat_model(start_guess()), "experiments": [exp],
                                      "method": method, "options": {"substeps": 2}}), SEAT_TRUTH


def msd_request(n: int):
    from greyfit.schemas import FitRequest
    t = np.arange(n) * 0.01
    model = msd_model()
    model["outputs"] = {"x": "x"}
    exp = msd_experiment(t, simulate_msd(t), noise=0.01, seed=1, outputs=("x",))
    # the rows say MS: named, since the default (auto) would run single shooting here
    return FitRequest.model_validate({"model": model, "experiments": [exp], "method": "multiple_shooting"}), MSD_TRUTH


def run_case(case: str, arg, env: dict, queue) -> None:
    os.environ.update(env)
    from greyfit.solvers.fit import fit_model
    req, truth = seat_request(arg) if case == "seat" else msd_request(arg)
    cold_wall, cold_cpu, res = _timed(fit_model, req)
    warm = [_timed(fit_model, req) for _ in range(3)]
    while sum(w[0] for w in warm) < 1.0 and len(warm) < 30:   # fast fits: a steadier median
        warm.append(_timed(fit_model, req))
    warm_wall, warm_cpu = (float(np.median([w[0] for w in warm])), float(np.median([w[1] for w in warm])))
    err = max(abs(res.parameters[k].value / truth[k] - 1) for k in truth if not res.parameters[k].fixed)
    queue.put((cold_wall, cold_cpu, warm_wall, warm_cpu, err, res.solver.iterations, res.solver.compiled,
               resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024))


VARIANTS = {
    "compiled": {"GREYFIT_COMPILE": "always"},
    "interpreted": {"GREYFIT_COMPILE": "never"},
    "generic graph": {"GREYFIT_COMPILE": "never", "GREYFIT_STRUCTURED_SHOOTING": "0"},
}


def main() -> None:
    # a spawned child imports numpy (and its OpenBLAS) before run_case sets its environment: the
    # thread count must be inherited, or numpy's BLAS runs 2 threads on small products (seat MS
    # warm 0.56 s instead of 0.29 s on a busy 2-core machine)
    os.environ["OPENBLAS_NUM_THREADS"] = "1"
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--skip-scipy", action="store_true")
    parser.add_argument("--sizes", type=int, nargs="*", default=[4000, 10000, 40000])
    parser.add_argument("--skip-generic-long", action="store_true",
                        help="do not run the generic graph on records above 10 000 samples")
    args = parser.parse_args()
    rows = []
    with tempfile.TemporaryDirectory() as cache:
        for method, tag in (("multiple_shooting", "MS"), ("single_shooting", "SS")):
            for variant, env in VARIANTS.items():
                env = dict(env, GREYFIT_CACHE_DIR=os.path.join(cache, f"seat-{tag}-{variant}"),
                           OPENBLAS_NUM_THREADS="1")
                rows.append((f"seat {tag}, 1000 samples, {variant}",
                             in_fresh_process(run_case, "seat", method, env), 8000))
        for variant in ("compiled", "interpreted"):
            env = dict(VARIANTS[variant], GREYFIT_CACHE_DIR=os.path.join(cache, f"ee-{variant}"),
                       OPENBLAS_NUM_THREADS="1")
            rows.append((f"seat equation error, {variant}",
                         in_fresh_process(run_case, "seat", "equation_error", env), 8000))
        for n in args.sizes:
            for variant, env in VARIANTS.items():
                if variant == "generic graph" and n > 10000 and args.skip_generic_long:
                    continue
                env = dict(env, GREYFIT_CACHE_DIR=os.path.join(cache, f"msd-{n}-{variant}"),
                           OPENBLAS_NUM_THREADS="1")
                rows.append((f"2-state MS, {n} samples, {variant}", in_fresh_process(run_case, "msd", n, env), n))
    scipy = None if args.skip_scipy else in_fresh_process(run_scipy, 0.01)

    print(f"{'case':44s} {'cold s':>7s} {'warm s':>7s} {'warm cpu':>8s} {'us/sample':>9s} {'max err':>8s} "
          f"{'iter':>4s} {'C':>5s} {'peak MB':>7s}")
    for name, (cw, _cc, ww, wc, err, it, is_c, mem), n in rows:
        print(f"{name:44s} {cw:7.3f} {ww:7.3f} {wc:8.3f} {1e6 * ww / n:9.1f} {err:8.1e} {it:4d} {str(is_c):>5s} "
              f"{mem:7.0f}")
    if scipy is not None:
        wall, _, est, nfev, ok, mem = scipy
        err = max(abs(est[k] / SEAT_TRUTH[k] - 1) for k in SEAT_TRUTH)
        print(f"{'seat, scipy least_squares + solve_ivp':44s} {wall:7.3f} {'':7s} {'':8s} {'':9s} {err:8.1e} "
              f"{nfev:4d} {'':5s} {mem:7.0f}")
    warm = {name: r[2] for name, r, _ in rows}
    base = warm.get("seat MS, 1000 samples, compiled")
    print("\nratios (warm):")
    if scipy is not None and base:
        print(f"  seat MS compiled vs scipy: {scipy[0] / base:6.0f}x faster (scipy's wall time)")
    if base:
        print(f"  seat MS compiled vs generic graph: {warm['seat MS, 1000 samples, generic graph'] / base:6.1f}x")
        ss = warm["seat SS, 1000 samples, compiled"]
        print(f"  seat SS compiled vs generic graph: {warm['seat SS, 1000 samples, generic graph'] / ss:6.1f}x")
    per = {n: warm.get(f"2-state MS, {n} samples, compiled") for n in args.sizes}
    if len(args.sizes) >= 2 and all(per.values()):
        lo, hi = min(args.sizes), max(args.sizes)
        growth = (per[hi] / hi) / (per[lo] / lo)
        print(f"  2-state MS time per sample, {hi} vs {lo} samples: {growth:4.2f}x (target <= 1.5x)")


if __name__ == "__main__":
    mp.set_start_method("spawn")
    main()
