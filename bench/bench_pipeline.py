"""Where a small warm fit spends its time: CPU per stage of `solvers.fit`, median over many fits.

    python bench/bench_pipeline.py [--fits 200]

Two cases, each in a fresh process with its compiled functions built first (what a warm service
worker runs): seed 000's seat model by equation error (1000 samples, 8 parameters, closed form) and
the README's mass-spring-damper by multiple shooting (101 samples, the synchronous example). The
stages are `solvers.fit`'s own steps, timed by wrapping them (nested stages are inside their
parent, so the column does not add up; "rest" is the total minus the top-level stages).

Peer, in the same run: scipy `lsq_linear` (bounded linear least squares, what lmfit or a script
would call) on the equation-error regressors greyfit builds — the bare solve, no diagnostics.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.bench_methods import in_fresh_process  # noqa: E402

# top-level steps of solvers/fit.py's outline and of the method object it builds
# (solvers/methods/batch.py), by (module or class, name); then stages nested in them (indented)
FIT = "greyfit.solvers.fit"
BATCH = "greyfit.solvers.methods.batch"
STEPS = [(FIT, "prepare_request"), (FIT, "compile_model"), (FIT, "prepare_experiments"), (FIT, "build_layout"),
         (BATCH, "build_equation_error"), (BATCH, "OutputErrorModel"), (BATCH, "build_multiple_shooting"),
         (FIT, "pre_fit_warnings"), (BATCH, "solve_from_starts"), (BATCH, "sensitivity_jacobian"),
         (BATCH + ":EquationErrorFit", "channels"), (BATCH + ":OutputErrorFit", "channels"),
         (FIT, "residual_analyses"), (FIT, "estimate_covariance"), (FIT, "_result"), (FIT, "_quality_inputs"),
         (FIT, "assess_fit")]
TOP = list(dict.fromkeys(name for _, name in STEPS))
NESTED = {"finite_result": "assess_fit"}


def msd_sync_request():
    from greyfit.schemas import FitRequest
    from tests.systems import msd_experiment, msd_model, simulate_msd
    t = np.linspace(0, 10, 101)
    return FitRequest.model_validate({"model": msd_model(c=0.5, k=3.0), "method": "multiple_shooting",
                                      "experiments": [msd_experiment(t, simulate_msd(t), noise=0.005, seed=1)]})


def run_case(case: str, fits: int, queue) -> None:
    os.environ.update({"GREYFIT_COMPILE": "always", "OPENBLAS_NUM_THREADS": "1"})
    import importlib

    import greyfit.solvers.checks.quality as quality
    import greyfit.solvers.fit as fit
    from bench.bench_speed import seat_request
    spent: dict[str, float] = defaultdict(float)

    def timed(owner, name):
        inner = getattr(owner, name)

        def wrapper(*args, **kwargs):
            c0 = time.process_time()
            try:
                return inner(*args, **kwargs)
            finally:
                spent[name] += time.process_time() - c0
        setattr(owner, name, wrapper)

    for where, name in STEPS:
        module, _, cls = where.partition(":")
        owner = importlib.import_module(module)
        timed(getattr(owner, cls) if cls else owner, name)
    timed(quality, "finite_result")
    req = seat_request("equation_error")[0] if case == "ee" else msd_sync_request()
    for _ in range(10):
        result = fit.fit_model(req)
    runs = []
    for _ in range(fits):
        spent.clear()
        c0 = time.process_time()
        fit.fit_model(req)
        runs.append(dict(spent, total=time.process_time() - c0))
    stages = {k: float(np.median([r.get(k, 0.0) for r in runs])) for k in ["total", *TOP, *NESTED]}
    stages["rest"] = float(np.median([r["total"] - sum(r.get(k, 0.0) for k in TOP) for r in runs]))
    peer = None
    if case == "ee":
        peer = _scipy_peer(req, fits)
    queue.put((stages, result.solver.compiled, result.solver.iterations, peer))


def _scipy_peer(req, fits: int) -> float | None:
    """Median CPU of scipy lsq_linear on greyfit's equation-error regressors, bounds included."""
    try:
        from scipy.optimize import lsq_linear
    except ImportError:
        return None
    from greyfit.solvers.data.experiments import prepare_experiments
    from greyfit.solvers.methods.equation_error import build_equation_error
    from greyfit.solvers.model.compiler import compile_model
    from greyfit.solvers.model.parameters import build_layout
    cm = compile_model(req.model)
    data = prepare_experiments(req.experiments, cm)
    layout = build_layout(req.model, [d.name for d in data])
    problem = build_equation_error(cm, data, layout, req.options).problem
    a, b = problem.evaluate_jacobian(np.zeros(layout.size))
    times = []
    for _ in range(fits):
        c0 = time.process_time()
        lsq_linear(a, -b, bounds=(problem.lbw, problem.ubw))
        times.append(time.process_time() - c0)
    return float(np.median(times))


def main() -> None:
    os.environ["OPENBLAS_NUM_THREADS"] = "1"
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--fits", type=int, default=200)
    args = parser.parse_args()
    cases = {"seat, equation error": in_fresh_process(run_case, "ee", args.fits),
             "msd 101, multiple shooting": in_fresh_process(run_case, "msd", args.fits)}
    names = list(cases)
    print(f"CPU ms per warm fit, median of {args.fits}")
    print(f"{'stage':28s} " + " ".join(f"{n:>28s}" for n in names))
    for key in ["total", *TOP, *NESTED, "rest"]:
        label = ("  " + key) if key in NESTED else key
        values = [cases[n][0].get(key, 0.0) for n in names]
        if key != "total" and max(values) < 5e-6:
            continue
        print(f"{label:28s} " + " ".join(f"{1e3 * v:28.3f}" for v in values))
    print(f"{'compiled C / iterations':28s} " + " ".join(f"{f'{c} / {i}':>28s}" for _, c, i, _ in cases.values()))
    peer = cases["seat, equation error"][3]
    if peer is not None:
        total = cases["seat, equation error"][0]["total"]
        solve = cases["seat, equation error"][0]["solve_from_starts"]
        print(f"\npeer: scipy lsq_linear on the same regressors (solve only, no diagnostics) {1e3 * peer:.3f} ms; "
              f"greyfit's solve stage {1e3 * solve:.3f} ms (scipy / greyfit {peer / max(solve, 1e-9):.2f}), "
              f"greyfit's whole fit {1e3 * total:.3f} ms")


if __name__ == "__main__":
    main()
