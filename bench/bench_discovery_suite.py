"""The discovery loop on a generated suite: systems × effects × measured outputs × noise × held inputs.

Each configuration is one system with one undeclared effect (or none: a complete model), measured in
some of its outputs, with white or AR(1) measurement noise of 1 % of the output's spread (ρ = 0.9 on
the mass-spring-damper's and the Duffing oscillator's position, 0.8 elsewhere), the input linear or
held between samples (declared as such: `input_interpolation`), and a validation record from another
seed. Five families: a mass-spring-damper (Coulomb friction, a cubic spring, quadratic drag, a sensor
offset), a Duffing oscillator, a pendulum by its angle (quadratic drag), two cascaded tanks by the lower
level (orifice outflows declared linear) and a motor whose speed sensor cannot see the sign
(tests/suite_systems.py). Every configuration runs over `--seeds` seeds (10 by default: every rate
below is over at least 10 runs). Truth is simulated with scipy, independently of greyfit.

Per configuration it prints:
- `recall`: runs whose steps include the true effect on the true equation; for a sensor offset on a
  linear system measured in position, where a constant force is exactly equivalent, either offset
  said to be `ambiguous` (n/a with no effect);
- `precision`: correct steps over all steps, pooled over the runs (n/a when nothing was added);
- `spurious`: mean number of steps that are not the true effect;
- `unexpl.`: share of runs that end with `unexplained` set;
- `wrong, unflagged`: share of runs that pass a wrong law off as the answer: a step that is not the
  true effect with the verdict `identified` (not `ambiguous`, not `approximates`), and no `unexplained`;
- `param err`: median over runs of the largest relative error of the declared free parameters (n/a for
  the tanks declared linear: their k1, k2 are not the orifice coefficients);
- `named`: what was added over all runs, by effect;
- `CPU s`, `wall s`: median CPU (process) and wall time of one discovery, in seconds;
- `SINDy`: where every state is measured and pySINDy is installed (`pip install -e .[bench]`),
  pySINDy (STLSQ, polynomial library of degree 3, derivatives by finite differences) on the same
  record: recall of the true term in the true equation (n/a where the law is not a polynomial),
  spurious terms, the same parameter error. Position-only configurations cannot be given to SINDy
  (it needs every state).

    OPENBLAS_NUM_THREADS=1 python bench/bench_discovery_suite.py [--seeds 10] [--quick] [--jobs 2]
        [--configs tanks,pendulum] [--budget 3600]
    OPENBLAS_NUM_THREADS=1 python bench/bench_discovery_suite.py --generated in,out,none [--seeds 10]
        [--first-seed 1] [--noise ar1] [--budget 300]

`--generated` runs the procedural generator instead (bench/discovery_generator.py: random chains of
mechanical, thermal, electrical, fluid, chemical and biological blocks, 2-5 states, a missing effect
in the library (`in`), outside it (`out`), beyond even its generic families (`beyond`) or none
(`none`)), and prints per group the share right (in: the true effect on the true equation, the
declared parameters within 5 %), honest (out, beyond: nothing
added or flagged — `unexplained`, `approximates` or `ambiguous` — or the right law from a family
that is it (Monod kinetics as a saturable rate, a dead zone), with every declared parameter within
10 %) or with nothing added (none), and the share passing a wrong law off as `identified`
with nothing flagged, with Wilson 95 % intervals; each run on stderr.

`--budget` is `discovery.time_budget_s` (CPU seconds, 3600 by default here against the request's
300): the suite measures what the search finds. `--jobs` runs seeds in worker processes (CPU times
stay per discovery; wall times then include the workers' contention). `--quick` runs 6 of the 24
configurations.
"""
from __future__ import annotations

import argparse
import multiprocessing
import os
import re
import sys
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from greyfit.schemas.discovery import DiscoverRequest  # noqa: E402
from greyfit.solvers.discovery import discover  # noqa: E402
from tests import coloured_records as cr  # noqa: E402
from tests import partial_systems as ps  # noqa: E402
from tests import suite_systems as ss  # noqa: E402
from tests.systems import MSD_TRUTH  # noqa: E402

N_DUFFING = 1001
# a generated effect and the library's name of the same law: Monod kinetics is a saturable rate, a thrust
# ∝ u·|u| a law of the input
SAME_LAW = {"monod": ("saturable_rate",), "thrust": ("input_law",)}
EFFECTS = ss.MSD_EFFECTS


@dataclass(frozen=True)
class Config:
    system: str      # "msd", "duffing" (its cubic undeclared), "pendulum", "tanks", "speed" (tests/suite_systems.py)
    effect: str      # a key of EFFECTS for msd; "cubic"/"drag"/"sqrt"/"abs" for the others; "none": complete model
    outputs: str     # "x" (position only) or "xv" (both states); the one measured output of the others
    noise: str       # "white" or "ar1"
    held: bool

    @property
    def label(self) -> str:
        return f"{self.system}+{self.effect} y={self.outputs} {self.noise}{' held' if self.held else ''}"


def _c(system: str, effect: str, outputs: str, noise: str, held: bool = False) -> Config:
    return Config(system, effect, outputs, noise, held)


CONFIGS = [
    # mass-spring-damper: every effect, position only or both states, white or AR(1), linear or held input
    _c("msd", "none", "x", "white"), _c("msd", "none", "x", "ar1", True), _c("msd", "none", "xv", "white", True),
    _c("msd", "coulomb", "x", "white"), _c("msd", "coulomb", "x", "ar1", True), _c("msd", "coulomb", "xv", "ar1", True),
    _c("msd", "cubic", "x", "ar1"), _c("msd", "cubic", "xv", "white", True),
    _c("msd", "drag", "x", "white", True), _c("msd", "drag", "xv", "ar1"),
    _c("msd", "offset", "x", "white", True), _c("msd", "offset", "x", "ar1"),
    # Duffing oscillator, position only: its cubic spring undeclared, or declared (nothing missing)
    _c("duffing", "cubic", "x", "white"), _c("duffing", "cubic", "x", "ar1", True),
    _c("duffing", "none", "x", "ar1", True),
    # pendulum by its angle: quadratic drag undeclared, or nothing missing
    _c("pendulum", "drag", "theta", "white"), _c("pendulum", "drag", "theta", "ar1", True),
    _c("pendulum", "none", "theta", "ar1", True),
    # two tanks, lower level only: outflows declared linear (orifice law missing), or declared as orifices
    _c("tanks", "sqrt", "h2", "white"), _c("tanks", "sqrt", "h2", "ar1", True), _c("tanks", "none", "h2", "ar1", True),
    # a motor's speed: a sensor that cannot see the sign, or a plain one
    _c("speed", "abs", "abs(w)", "white"), _c("speed", "abs", "abs(w)", "ar1", True), _c("speed", "none", "w", "ar1"),
]
QUICK = [CONFIGS[0], CONFIGS[3], CONFIGS[7], CONFIGS[12], CONFIGS[15], CONFIGS[21]]


def case_of(cfg: Config, seed: int) -> ss.Case:
    """The request (estimation and validation records) of one configuration and seed, and its truth."""
    if cfg.system == "duffing":
        cubic_missing = cfg.effect == "cubic"
        rec = cr.duffing_record(N_DUFFING, seed, kind=cfg.noise, level=0.01, held=cfg.held)
        val = cr.duffing_record(N_DUFFING, seed + 500, kind=cfg.noise, level=0.01, held=cfg.held, name="val")
        model = ps.duffing_model() if cubic_missing else cr.duffing_complete_model()
        truth = {"d": ps.DUFFING_TRUTH["d"], "k": ps.DUFFING_TRUTH["k"]}
        if not cubic_missing:
            truth["k3"] = ps.DUFFING_TRUTH["k3"]
        case = ss.Case({"model": model, "experiments": [rec], "validation": [val]}, truth,
                       "cubic_stiffness" if cubic_missing else None, "yd")
    elif cfg.system == "msd" and cfg.effect == "offset":
        case = ss.sensor_offset_case(cfg.noise, cfg.held, seed)
    elif cfg.system == "msd":
        case = ss.msd_case(cfg.effect, cfg.outputs, cfg.noise, cfg.held, seed)
    else:
        case = ss.FAMILIES[cfg.system](cfg.effect != "none", cfg.noise, cfg.held, seed)
    body = case.body
    body.setdefault("method", "multiple_shooting")
    body["options"] = {**body.get("options", {}), "input_interpolation": "zoh" if cfg.held else "foh"}
    return case


def is_right(step, case: ss.Case, ambiguous: bool) -> bool:
    """A step is the true effect on the true equation; where two laws are exactly equivalent on these
    outputs (a sensor offset and a constant force on a linear system measured in position), either
    one, said to be `ambiguous`."""
    if case.effect is None:
        return False
    if case.effect == "output_offset" and step.effect in ("output_offset", "offset"):
        return ambiguous or step.effect == "output_offset"
    return step.effect in SAME_LAW.get(case.effect, (case.effect,)) and \
        case.equation in re.split(r"[ ,]+", step.equation)


def run_greyfit(case: ss.Case, budget: float) -> dict:
    case.body["discovery"] = {**case.body.get("discovery", {}), "time_budget_s": budget}
    t0, c0 = time.perf_counter(), time.process_time()
    res = discover(DiscoverRequest.model_validate(case.body))
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    correct = [s for s in res.steps if is_right(s, case, res.ambiguous)]
    # a wrong law passed off as the answer: named as identified, and the result does not say that
    # something is left unexplained
    confident_wrong = res.unexplained is None and any(
        s.verdict == "identified" and s not in correct for s in res.steps)
    err = max((abs(abs(res.fit.parameters[k].value) - v) / abs(v) for k, v in case.truth.items()), default=np.nan)
    return {"found": bool(correct), "steps": len(res.steps), "correct": min(len(correct), 1),
            "unexplained": res.unexplained is not None, "confident_wrong": confident_wrong, "err": err,
            "time": wall, "cpu": cpu,
            "named": [s.effect for s in res.steps]}


def run_sindy(cfg: Config, case: ss.Case) -> dict | None:
    """pySINDy on the same record where every state is measured (the mass-spring-damper with both
    states, the motor's plain speed sensor)."""
    if not (cfg.system == "msd" and cfg.outputs == "xv" or cfg.system == "speed" and cfg.effect == "none"):
        return None
    try:
        import pysindy
    except ImportError:
        return None
    exp = case.body["experiments"][0]
    t = np.array(exp["time"])
    x = np.column_stack([exp["outputs"][o] for o in exp["outputs"]])
    u = np.array(exp["inputs"]["u"])[:, None]
    model = pysindy.SINDy(optimizer=pysindy.STLSQ(threshold=0.05), feature_library=pysindy.PolynomialLibrary(3))
    model.fit(x, t=t, u=u)
    names = model.get_feature_names()
    coef = model.coefficients()[-1]    # the last state's equation: v' = (u - c v - k x - effect)/m, w' = -b w + K u
    if cfg.system == "speed":
        est = {"b": -coef[names.index("x0")], "K": coef[names.index("u0")]}
        expected, term = {"x0", "u0"}, None
    else:
        m = MSD_TRUTH["m"]
        est = {"c": -coef[names.index("x1")] * m, "k": -coef[names.index("x0")] * m}
        term = EFFECTS[cfg.effect][3]
        expected = {"x0", "x1", "u0"} | ({term} if term else set())
    spurious = sum(1 for n, v in zip(names, coef) if v != 0 and n not in expected and n != "1")
    found = term is not None and coef[names.index(term)] != 0
    err = max(abs(est[k] - v) / abs(v) for k, v in case.truth.items())
    return {"found": found, "spurious": spurious, "err": err}


def run_seed(job: tuple[Config, int, float]) -> tuple[dict, dict | None]:
    cfg, seed, budget = job
    case = case_of(cfg, seed)   # the same records for both
    return run_greyfit(case, budget), run_sindy(cfg, case)


def summarise(cfg: Config, runs: list[dict], sindy: list[dict]) -> str:
    has_effect = cfg.effect != "none"
    recall = f"{np.mean([r['found'] for r in runs]):.2f}" if has_effect else "n/a"
    steps = sum(r["steps"] for r in runs)
    precision = f"{sum(r['correct'] for r in runs) / steps:.2f}" if steps and has_effect else \
        ("n/a" if not steps else "0.00")
    spurious = np.mean([r["steps"] - r["correct"] for r in runs])
    unexpl = np.mean([r["unexplained"] for r in runs])
    confident_wrong = np.mean([r["confident_wrong"] for r in runs])
    errs = [r["err"] for r in runs if np.isfinite(r["err"])]
    err = f"{100 * np.median(errs):.1f} %" if errs else "n/a"
    wall = np.median([r["time"] for r in runs])
    cpu = np.median([r["cpu"] for r in runs])
    others = Counter(e for r in runs for e in r["named"])
    named = ", ".join(f"{k} {v}" for k, v in others.most_common()) or "nothing"
    s = "-"
    if sindy:
        term = cfg.system == "msd" and EFFECTS[cfg.effect][3]
        s_recall = f"{np.mean([r['found'] for r in sindy]):.2f}" if has_effect and term else "n/a"
        s = (f"recall {s_recall}, spurious {np.mean([r['spurious'] for r in sindy]):.1f}, "
             f"err {100 * np.median([r['err'] for r in sindy]):.1f} %")
    return (f"| {cfg.label} | {len(runs)} | {recall} | {precision} | {spurious:.2f} | {unexpl:.2f} | "
            f"{confident_wrong:.2f} | {err} | {named} | {cpu:.1f} | {wall:.1f} | {s} |")


# --- the procedural generator (bench/discovery_generator.py) ----------------------------------------

def wilson(k: int, n: int, z: float = 1.96) -> str:
    """k/n with its Wilson 95 % interval."""
    if n == 0:
        return "n/a"
    p = k / n
    d = 1 + z * z / n
    mid = (p + z * z / (2 * n)) / d
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return f"{k}/{n} ({100 * p:.0f} %, {100 * max(mid - half, 0):.0f}–{100 * min(mid + half, 1):.0f} %)"


def judge_generated(group: str, case: ss.Case, res) -> dict:
    """One generated run judged: right (in), honest (out), nothing added (none), and wrong-unflagged."""
    errs = [abs(res.fit.parameters[k].value - v) / abs(v) for k, v in case.truth.items() if k in res.fit.parameters]
    err = max(errs, default=np.inf)
    correct = [s for s in res.steps if is_right(s, case, res.ambiguous)]
    flagged = res.unexplained is not None or any(s.verdict != "identified" for s in res.steps)
    wrong_unflagged = any(s not in correct for s in res.steps) and not flagged
    if group == "in":
        ok = bool(correct) and err <= 0.05
    elif group in ("out", "beyond"):
        # honest: the right law (a generic family that is the law), or nothing added, or what was
        # added flagged; every declared parameter within 10 % either way
        ok = (bool(correct) or not res.steps or flagged) and err <= 0.10 and not wrong_unflagged
    else:
        ok = not res.steps
    return {"ok": ok, "wrong_unflagged": wrong_unflagged, "err": err, "named": [s.effect for s in res.steps],
            "verdicts": [s.verdict for s in res.steps], "unexplained": res.unexplained is not None}


def run_generated(job: tuple[str, int, float, str]) -> dict:
    from bench.discovery_generator import describe, generate
    group, seed, budget, noise = job
    case = generate(group, seed, noise=noise)
    case.body["discovery"] = {"time_budget_s": budget}
    c0 = time.process_time()
    try:
        res = discover(DiscoverRequest.model_validate(case.body))
    except Exception as exc:   # a traceback is a finding of the bench, not its end
        return {"ok": False, "wrong_unflagged": False, "err": np.inf, "named": [f"ERROR {exc!r}"[:120]],
                "verdicts": [], "unexplained": False, "cpu": time.process_time() - c0, "seed": seed,
                "what": describe(case)}
    out = judge_generated(group, case, res)
    out.update(cpu=time.process_time() - c0, seed=seed, what=describe(case))
    return out


def generated_main(groups: list[str], seeds: list[int], jobs: int, budget: float, noise: str) -> None:
    print("| group | noise | runs | right / honest / nothing added | wrong law `identified` unflagged | "
          "median CPU s | max CPU s |")
    print("|---|---|---|---|---|---|---|")
    with multiprocessing.get_context("spawn").Pool(jobs, maxtasksperchild=10) as pool:
        for group in groups:
            runs = []
            for r in pool.imap_unordered(run_generated, [(group, s, budget, noise) for s in seeds]):
                runs.append(r)
                print(f"  seed {r['seed']}: {r['what']}: ok={r['ok']} err={100 * r['err']:.1f} % "
                      f"named={list(zip(r['named'], r['verdicts']))} unexplained={r['unexplained']} "
                      f"cpu={r['cpu']:.1f}", file=sys.stderr, flush=True)
            cpu = [r["cpu"] for r in runs]
            print(f"| {group} | {noise} | {len(runs)} | {wilson(sum(r['ok'] for r in runs), len(runs))} | "
                  f"{wilson(sum(r['wrong_unflagged'] for r in runs), len(runs))} | {np.median(cpu):.1f} | "
                  f"{max(cpu):.1f} |", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--generated", default="", help="run the procedural generator's groups instead "
                                                    "(comma-separated of in, out, none)")
    ap.add_argument("--first-seed", type=int, default=1)
    ap.add_argument("--noise", default="ar1", help="generator's noise: white or ar1")
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--quick", action="store_true", help=f"{len(QUICK)} configurations only")
    ap.add_argument("--configs", default="", help="only configurations whose label contains one of these "
                                                  "comma-separated strings (e.g. tanks,pendulum)")
    ap.add_argument("--jobs", type=int, default=1, help="worker processes (one discovery each)")
    ap.add_argument("--budget", type=float, default=3600.0, help="discovery.time_budget_s, CPU seconds")
    args = ap.parse_args()
    if args.generated:
        seeds = list(range(args.first_seed, args.first_seed + args.seeds))
        generated_main(args.generated.split(","), seeds, args.jobs, args.budget, args.noise)
        return
    configs = QUICK if args.quick else CONFIGS
    if args.configs:
        configs = [c for c in configs if any(k in c.label for k in args.configs.split(","))]
    print(f"{len(configs)} configurations × {args.seeds} seeds = {len(configs) * args.seeds} cases, "
          f"{args.jobs} worker(s); load average before: {' '.join(f'{x:.2f}' for x in os.getloadavg())}\n")
    print("| configuration | runs | recall | precision | spurious | unexpl. | wrong, unflagged | param err | named "
          "| CPU s | wall s | pySINDy |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    started = time.perf_counter()
    cpu_total = 0.0
    with multiprocessing.get_context("spawn").Pool(args.jobs, maxtasksperchild=20) as pool:
        for cfg in configs:
            out = pool.map(run_seed, [(cfg, seed, args.budget) for seed in range(1, args.seeds + 1)])
            runs = [r for r, _ in out]
            cpu_total += sum(r["cpu"] for r in runs)
            print(summarise(cfg, runs, [s for _, s in out if s is not None]), flush=True)
    print(f"\ntotal {time.perf_counter() - started:.0f} s wall, {cpu_total:.0f} s CPU in the discoveries; "
          f"load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
