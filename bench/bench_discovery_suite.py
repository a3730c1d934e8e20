"""The discovery loop on a generated suite: systems × effects × measured outputs × noise × held inputs.

Each configuration is one system with one undeclared effect (or none), measured in some of its
outputs, with white or AR(1) measurement noise (ρ = 0.9 on the position, 0.8 on the speed) of 1 % of
the output's spread, the input linear or held between samples, a validation record from another
seed; every configuration runs over
`--seeds` seeds (10 by default: every rate below is over at least 10 runs). Truth is simulated with
scipy (tests/coloured_records.py, tests/systems.py), independently of greyfit.

Per configuration it prints:
- `recall`: runs whose steps include the true effect on the true equation (n/a with no effect);
- `precision`: correct steps over all steps, pooled over the runs (n/a when nothing was added);
- `spurious`: mean number of steps that are not the true effect;
- `unexpl.`: runs that end with `unexplained` set;
- `param err`: median over runs of the largest relative error of the declared free parameters;
- `CPU s`, `wall s`: median CPU (process) and wall time of one discovery, in seconds (the load
  average is printed before and after: on a shared machine the wall time is mostly the load's);
- `SINDy`: where every state is measured and pySINDy is installed (`pip install -e .[bench]`),
  pySINDy (STLSQ, polynomial library of degree 3, derivatives by finite differences) on the same
  record: recall of the true term in the true equation, spurious terms, the same parameter error.
  Position-only configurations cannot be given to SINDy (it needs every state).

    OPENBLAS_NUM_THREADS=1 python bench/bench_discovery_suite.py [--seeds 10] [--quick] [--budget 3600]

`--budget` is `discovery.time_budget_s` (wall seconds, 3600 by default here against the request's
300): the suite measures what the search finds, not how loaded the machine is.

`--quick` runs 4 of the configurations (40 cases with the default seeds).
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from greyfit.schemas.discovery import DiscoverRequest  # noqa: E402
from greyfit.solvers.discovery import discover  # noqa: E402
from tests import coloured_records as cr  # noqa: E402
from tests import partial_systems as ps  # noqa: E402
from tests.systems import MSD_TRUTH, msd_model  # noqa: E402

N_MSD, N_DUFFING = 1001, 1001
EFFECTS = {   # name -> (force added to m x'', the loop's effect name, its equation, SINDy's term)
    "none": (None, None, None, None),
    "coulomb": (lambda x, v: 0.5 * np.tanh(v / 1e-3), "coulomb", "v", None),
    "cubic": (lambda x, v: 3.0 * x ** 3, "cubic_stiffness", "v", "x0^3"),
    "drag": (lambda x, v: 0.6 * v * np.abs(v), "quadratic_drag", "v", None),
}


@dataclass(frozen=True)
class Config:
    system: str      # "msd" (x'' form) or "duffing" (its cubic undeclared)
    effect: str
    outputs: str     # "x" (position only) or "xv" (both states)
    noise: str       # "white" or "ar1"
    held: bool

    @property
    def label(self) -> str:
        return f"{self.system}+{self.effect} y={self.outputs} {self.noise}{' held' if self.held else ''}"


CONFIGS = [
    Config("msd", "none", "x", "white", False), Config("msd", "none", "x", "ar1", True),
    Config("msd", "coulomb", "x", "white", False), Config("msd", "coulomb", "xv", "ar1", True),
    Config("msd", "cubic", "x", "ar1", False), Config("msd", "cubic", "xv", "white", True),
    Config("msd", "drag", "x", "white", True), Config("duffing", "cubic", "x", "white", False),
]
QUICK = [CONFIGS[0], CONFIGS[2], CONFIGS[5], CONFIGS[7]]


def _msd_body(cfg: Config, seed: int) -> tuple[dict, dict]:
    force = EFFECTS[cfg.effect][0]
    rec = {}
    for name, s, x0, t0 in (("est", seed, (0.1, 0.0), 0.0), ("val", seed + 500, (-0.2, 0.1), 20.0)):
        rec[name] = _msd_states_record(N_MSD, s, cfg, force, name, x0, t0)
    model = msd_model()
    model["outputs"] = {o: o for o in ("x", "v")} if cfg.outputs == "xv" else {"x": "x"}
    return model, rec


def _msd_states_record(n, seed, cfg, force, name, x0, t0):
    """Like tests/coloured_records.msd_record, with the speed measured too when asked."""
    base = cr.msd_record(n, seed, kind=cfg.noise, level=0.01, extra_force=force, held=cfg.held, name=name,
                         x0=x0, t0=t0)
    if cfg.outputs == "xv":
        t = np.array(base["time"])
        speed = np.gradient(_clean_position(n, seed, cfg, force, x0, t0), t)
        noise = cr.coloured_noise(n, cfg.noise if cfg.noise != "ar1" else "ar1", np.random.default_rng(7000 + seed),
                                  rho=0.8)
        base["outputs"]["v"] = (speed + 0.01 * np.std(speed) * noise).tolist()
    return base


def _clean_position(n, seed, cfg, force, x0, t0):
    rec = cr.msd_record(n, seed, kind="white", level=0.0, extra_force=force, held=cfg.held, x0=x0, t0=t0)
    return np.array(rec["outputs"]["x"])


def body_of(cfg: Config, seed: int) -> tuple[dict, dict[str, float]]:
    if cfg.system == "duffing":
        rec = cr.duffing_record(N_DUFFING, seed, kind=cfg.noise, level=0.01, held=cfg.held)
        val = cr.duffing_record(N_DUFFING, seed + 500, kind=cfg.noise, level=0.01, held=cfg.held, name="val")
        body = {"model": ps.duffing_model(), "experiments": [rec], "validation": [val]}
        truth = {"d": ps.DUFFING_TRUTH["d"], "k": ps.DUFFING_TRUTH["k"]}
    else:
        model, rec = _msd_body(cfg, seed)
        body = {"model": model, "experiments": [rec["est"]], "validation": [rec["val"]]}
        truth = {"c": MSD_TRUTH["c"], "k": MSD_TRUTH["k"]}
    body["method"] = "multiple_shooting"
    body["options"] = {"input_interpolation": "zoh" if cfg.held else "foh"}
    return body, truth


def run_greyfit(cfg: Config, seed: int, budget: float) -> dict:
    body, truth = body_of(cfg, seed)
    body["discovery"] = {**body.get("discovery", {}), "time_budget_s": budget}
    t0, c0 = time.perf_counter(), time.process_time()
    res = discover(DiscoverRequest.model_validate(body))
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    _, effect, equation, _ = EFFECTS[cfg.effect]
    equation = "yd" if cfg.system == "duffing" else equation   # the Duffing model names its speed yd
    correct = [s for s in res.steps if s.effect == effect and s.equation == equation]
    err = max(abs(res.fit.parameters[k].value - v) / abs(v) for k, v in truth.items())
    return {"found": bool(correct), "steps": len(res.steps), "correct": min(len(correct), 1),
            "unexplained": res.unexplained is not None, "err": err, "time": wall, "cpu": cpu}


def run_sindy(cfg: Config, seed: int) -> dict | None:
    if cfg.outputs != "xv" and cfg.system == "msd" or cfg.system != "msd":
        return None
    try:
        import pysindy
    except ImportError:
        return None
    body, truth = body_of(cfg, seed)
    exp = body["experiments"][0]
    t = np.array(exp["time"])
    x = np.column_stack([exp["outputs"]["x"], exp["outputs"]["v"]])
    u = np.array(exp["inputs"]["u"])[:, None]
    model = pysindy.SINDy(optimizer=pysindy.STLSQ(threshold=0.05), feature_library=pysindy.PolynomialLibrary(3))
    model.fit(x, t=t, u=u)
    names = model.get_feature_names()
    coef = model.coefficients()[1]    # the v equation: v' = (u - c v - k x - effect)/m
    m = MSD_TRUTH["m"]
    c, k = -coef[names.index("x1")] * m, -coef[names.index("x0")] * m
    term = EFFECTS[cfg.effect][3]
    expected = {"1", "x0", "x1", "u0"} if cfg.effect == "none" else {"x0", "x1", "u0", term}
    spurious = sum(1 for n, v in zip(names, coef) if v != 0 and n not in expected and n != "1")
    found = term is not None and coef[names.index(term)] != 0
    err = max(abs(c - truth["c"]) / truth["c"], abs(k - truth["k"]) / truth["k"])
    return {"found": found, "spurious": spurious, "err": err}


def summarise(cfg: Config, runs: list[dict], sindy: list[dict]) -> str:
    has_effect = cfg.effect != "none"
    recall = f"{np.mean([r['found'] for r in runs]):.2f}" if has_effect else "n/a"
    steps = sum(r["steps"] for r in runs)
    precision = f"{sum(r['correct'] for r in runs) / steps:.2f}" if steps and has_effect else \
        ("n/a" if not steps else "0.00")
    spurious = np.mean([r["steps"] - r["correct"] for r in runs])
    unexpl = np.mean([r["unexplained"] for r in runs])
    err = np.median([r["err"] for r in runs])
    wall = np.median([r["time"] for r in runs])
    cpu = np.median([r["cpu"] for r in runs])
    s = "-"
    if sindy:
        s_recall = f"{np.mean([r['found'] for r in sindy]):.2f}" if has_effect and EFFECTS[cfg.effect][3] else "n/a"
        s = (f"recall {s_recall}, spurious {np.mean([r['spurious'] for r in sindy]):.1f}, "
             f"err {100 * np.median([r['err'] for r in sindy]):.1f} %")
    return (f"| {cfg.label} | {len(runs)} | {recall} | {precision} | {spurious:.2f} | {unexpl:.2f} | "
            f"{100 * err:.1f} % | {cpu:.1f} | {wall:.1f} | {s} |")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--quick", action="store_true", help="4 configurations only")
    ap.add_argument("--budget", type=float, default=3600.0, help="discovery.time_budget_s, wall seconds")
    args = ap.parse_args()
    configs = QUICK if args.quick else CONFIGS
    print(f"{len(configs)} configurations × {args.seeds} seeds = {len(configs) * args.seeds} cases; "
          f"load average before: {' '.join(f'{x:.2f}' for x in os.getloadavg())}\n")
    print("| configuration | runs | recall | precision | spurious | unexpl. | param err | CPU s | wall s | pySINDy |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    started, cpu0 = time.perf_counter(), time.process_time()
    for cfg in configs:
        runs = [run_greyfit(cfg, seed, args.budget) for seed in range(1, args.seeds + 1)]
        sindy = [r for r in (run_sindy(cfg, seed) for seed in range(1, args.seeds + 1)) if r is not None]
        print(summarise(cfg, runs, sindy), flush=True)
    print(f"\ntotal {time.perf_counter() - started:.0f} s wall, {time.process_time() - cpu0:.0f} s CPU; "
          f"load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
