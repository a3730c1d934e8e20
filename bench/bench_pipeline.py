"""Where a warm fit spends its time: CPU per stage of `solvers.fit`, median over many fits.

    python bench/bench_pipeline.py [--fits 100] [--rounds 3] [--cases msd101-ms seat-ee ...]
                                   [--baseline /path/to/other/venv/bin/python]

Cases (2 states × 101 samples, seed 000's seat model with 8 states × 1000 samples, 2 states × 40 000
samples), each by equation error (`-ee`), by multiple shooting (`-ms`) and by the default method
(`-auto`: single shooting on these, as the method choice decides; also 2 states × 401 samples).
Every measurement runs in a fresh process with its compiled functions built first (what a warm
service worker runs). The stages are `solvers.fit`'s own steps, timed by wrapping them (nested
stages, indented, are inside their parent, so the column does not add up; "rest" is the total minus
the top-level stages).

With `--baseline`, the same cases also run under another interpreter (another checkout of greyfit,
e.g. the main branch in its own venv), interleaved A B A B over `--rounds` rounds, and the table
shows both with the ratio; the results of the two are compared (largest relative difference of the
estimates, standard errors, cost and residual diagnostics) so that a faster pipeline that answers
differently shows. The machine's load average is printed before and after.

Peer, in the same run: scipy `lsq_linear` (bounded linear least squares, what lmfit or a script
would call) on the equation-error regressors greyfit builds for the seat — the bare solve, no
diagnostics.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

# top-level steps of solvers/fit.py's outline and of the method object it builds
# (solvers/methods/batch.py), by (module or class, name); then stages nested in them (indented)
FIT = "greyfit.solvers.fit"
BATCH = "greyfit.solvers.methods.batch"
VERDICT = "greyfit.solvers.checks.verdict"
STEPS = [(FIT, "prepare_request"), (FIT, "choose_substeps"), (FIT, "compile_model"), (FIT, "prepare_experiments"),
         (FIT, "build_layout"), (BATCH, "build_equation_error"), (BATCH, "OutputErrorModel"),
         (BATCH, "build_multiple_shooting"), (BATCH, "build_single_shooting"), (BATCH, "choose_shooting"),
         (FIT, "pre_fit_warnings"), (BATCH, "solve_from_starts"),
         (BATCH, "sensitivity_jacobian"), (FIT, "equation_error_bias_warnings"),
         (BATCH + ":EquationErrorFit", "channels"), (BATCH + ":OutputErrorFit", "channels"),
         (FIT, "residual_analyses"), (FIT, "row_keys"), (FIT, "estimate_covariance"), (FIT + ":_Fit", "_draft_result"),
         (FIT + ":_Fit", "_quality_inputs"), (FIT, "assess_fit"), (FIT, "substeps_retry"), (FIT, "review_fit")]
TOP = list(dict.fromkeys(name for _, name in STEPS))
NESTED = [("greyfit.solvers.checks.quality", "finite_result", "assess_fit"),
          (VERDICT, "missing_effect_warnings", "review_fit"), (VERDICT, "noise_level_warnings", "review_fit")]
CASES = ["msd101-ee", "msd101-ms", "seat-ee", "seat-ms", "msd40000-ee", "msd40000-ms",
         "msd101-auto", "msd401-auto", "seat-auto", "msd40000-auto"]
# fewer fits: ~fits / this
SLOW = {"msd40000-ee": 10, "msd40000-ms": 40, "seat-ms": 4, "seat-auto": 4, "msd40000-auto": 20}


def msd_request(n: int, method: str):
    """The README's mass-spring-damper, both states measured with noise 0.005: 101 samples over
    10 s (the synchronous example), or `n` samples at 100 Hz."""
    from greyfit.schemas import FitRequest
    from tests.systems import msd_experiment, msd_model, simulate_msd
    t = np.linspace(0, 10, n) if n <= 1000 else np.arange(n) * 0.01
    return FitRequest.model_validate({"model": msd_model(c=0.5, k=3.0), "method": method,
                                      "experiments": [msd_experiment(t, simulate_msd(t), noise=0.005, seed=1)]})


def case_request(case: str):
    from bench.bench_speed import seat_request
    system, _, short = case.partition("-")
    method = {"ee": "equation_error", "ms": "multiple_shooting", "auto": "auto"}[short]
    return seat_request(method)[0] if system == "seat" else msd_request(int(system[3:]), method)


def fingerprint(result) -> dict[str, float]:
    """The numbers a faster pipeline must not change: estimates, standard errors, cost, diagnostics."""
    out = {"cost": result.metrics.cost}
    for name, p in result.parameters.items():
        out[f"value.{name}"] = p.value
        if p.stderr is not None:
            out[f"stderr.{name}"] = p.stderr
    for a in result.residual_analysis:
        out[f"rmse.{a.output}"] = a.rmse
        out[f"fit.{a.output}"] = a.fit_percent
        out[f"white.{a.output}"] = a.whiteness.max_abs
        out.update({f"acf{k}.{a.output}": v for k, v in enumerate(a.autocorrelation)})
        out.update({f"indep.{a.output}.{u}": t.max_abs for u, t in a.independence.items()})
    out[f"warnings {' '.join(sorted(w.code for w in result.warnings))} {result.quality}"] = 1.0
    return {k: float(v) for k, v in out.items() if v is not None}


def run_case(case: str, fits: int) -> dict:
    """Median CPU per stage (and the total's wall) over `fits` warm fits of `case`, in this process."""
    import importlib

    import greyfit.solvers.fit as fit
    spent: dict[str, float] = defaultdict(float)

    def timed(owner, name):
        inner = getattr(owner, name, None)
        if inner is None:   # a stage the other checkout does not have
            return

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
    for module, name, _ in NESTED:
        timed(importlib.import_module(module), name)
    req = case_request(case)
    for _ in range(3 if case in SLOW else 10):
        result = fit.fit_model(req)
    runs = []
    for _ in range(fits):
        spent.clear()
        c0, w0 = time.process_time(), time.perf_counter()
        fit.fit_model(req)
        runs.append(dict(spent, total=time.process_time() - c0, wall=time.perf_counter() - w0))
    keys = ["total", "wall", *TOP, *(name for _, name, _ in NESTED)]
    stages = {k: float(np.median([r.get(k, 0.0) for r in runs])) for k in keys}
    stages["rest"] = float(np.median([r["total"] - sum(r.get(k, 0.0) for k in TOP) for r in runs]))
    return {"stages": stages, "compiled": result.solver.compiled, "iterations": result.solver.iterations,
            "fingerprint": fingerprint(result)}


def scipy_peer(fits: int) -> float | None:
    """Median CPU of scipy lsq_linear on greyfit's equation-error regressors of the seat, bounds included."""
    try:
        from scipy.optimize import lsq_linear
    except ImportError:
        return None
    from greyfit.solvers.data.experiments import prepare_experiments
    from greyfit.solvers.methods.equation_error import build_equation_error
    from greyfit.solvers.model.compiler import compile_model
    from greyfit.solvers.model.parameters import build_layout
    req = case_request("seat-ee")
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


def in_subprocess(python: str, *args: str) -> dict:
    """Run this script's worker under `python` (a fresh process, its own greyfit install)."""
    # set before the child imports numpy: OpenBLAS reads its thread count when it loads
    env = dict(os.environ, GREYFIT_COMPILE="always", OPENBLAS_NUM_THREADS="1")
    out = subprocess.run([python, str(Path(__file__).resolve()), "--worker", *args], check=True,
                         capture_output=True, text=True, cwd=ROOT, env=env).stdout
    return json.loads(out.strip().splitlines()[-1])


def largest_difference(a: dict[str, float], b: dict[str, float]) -> tuple[float, str]:
    """Largest relative difference between two fingerprints and its key (inf where the keys differ)."""
    if set(a) != set(b):
        return float("inf"), " / ".join(sorted(set(a) ^ set(b)))
    diffs = {k: abs(a[k] - b[k]) / max(abs(a[k]), abs(b[k]), 1e-300) if a[k] != b[k] else 0.0 for k in a}
    key = max(diffs, key=lambda k: diffs[k])
    return diffs[key], key


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--fits", type=int, default=100)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--cases", nargs="+", default=CASES, choices=CASES)
    parser.add_argument("--baseline", help="python of another greyfit install to compare with (B)")
    parser.add_argument("--worker", nargs=2, metavar=("CASE", "FITS"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        case, fits = args.worker
        print(json.dumps(run_case(case, int(fits)) if case != "scipy" else {"peer": scipy_peer(int(fits))}))
        return
    pythons = {"A": sys.executable} | ({"B": args.baseline} if args.baseline else {})
    print(f"load average before: {' '.join(f'{v:.2f}' for v in os.getloadavg())}; CPU ms per warm fit, "
          f"median over rounds of the median of each round's fits (A = this checkout"
          + (f", B = {args.baseline})" if args.baseline else ")"))
    for case in args.cases:
        fits = max(3, args.fits // SLOW.get(case, 1))
        rounds: dict[str, list[dict]] = {k: [] for k in pythons}
        for r in range(args.rounds):
            for key in (pythons if r % 2 == 0 else reversed(list(pythons))):   # A B, B A, ...: interleaved
                rounds[key].append(in_subprocess(pythons[key], case, str(fits)))
        _print_case(case, fits, rounds)
    peer = in_subprocess(sys.executable, "scipy", str(args.fits))["peer"] if "seat-ee" in args.cases else None
    if peer is not None:
        print(f"\npeer: scipy lsq_linear on the seat's equation-error regressors (solve only, no diagnostics) "
              f"{1e3 * peer:.3f} ms CPU")
    print(f"load average after: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")


def _print_case(case: str, fits: int, rounds: dict[str, list[dict]]) -> None:
    keys = list(rounds)
    med = {k: {s: float(np.median([r["stages"][s] for r in rounds[k]])) for s in rounds[k][0]["stages"]}
           for k in keys}
    head = f"{case} ({fits} fits × {len(rounds['A'])} rounds)"
    print(f"\n{head:34s}" + "".join(f"{k:>10s}" for k in keys) + ("   B / A" if len(keys) > 1 else ""))
    nested = {name: parent for _, name, parent in NESTED}
    for stage in ["total", "wall", *TOP, *nested, "rest"]:
        values = [med[k].get(stage, 0.0) for k in keys]
        if stage not in ("total", "wall", "rest") and max(values) < 5e-6:
            continue
        label = ("  " + stage) if stage in nested else stage + (" (wall)" if stage == "wall" else "")
        ratio = f"{values[1] / values[0]:8.2f}" if len(keys) > 1 and values[0] > 0 else ""
        print(f"{label:34s}" + "".join(f"{1e3 * v:10.3f}" for v in values) + ratio)
    first = {k: rounds[k][0] for k in keys}
    print(f"{'compiled C / iterations':34s}" + "".join(f"{str(first[k]['compiled'])[0]} / {first[k]['iterations']:<4d}"
                                                        .rjust(10) for k in keys))
    if len(keys) > 1:
        diff, where = largest_difference(first["A"]["fingerprint"], first["B"]["fingerprint"])
        print(f"{'results A vs B: largest rel. diff':34s}{diff:10.1e}  ({where})")


if __name__ == "__main__":
    main()
