"""Experiment design measured against simulated truth (docs/design.md).

Two tables, over random systems (a new system per seed):

information  Systems recorded with one step (mechanical: a mass-spring-damper; thermal: two nodes, the
             far one measured; fluid: two tanks in series with linearised outflows, the lower level
             measured, the upper outflow known).
             The D-optimal input of the same length and amplitude is designed; both records are simulated
             and fitted under --draws noise draws each. Per family: the median over systems of the
             worst-excited parameter's spread ratio (step / designed, Monte Carlo), the share of systems
             where it is ≥ 3 (Wilson interval), and the predicted standard error against the Monte Carlo
             spread (median and range of predicted/spread over every parameter).
discrimination
             A mass-spring-damper with Coulomb friction (the truth) or quadratic damping, both small,
             recorded with one step; the loop (POST /v1/discover's `discover`) runs on the step record and
             on a record of the T-optimal input designed against the rivals the loop sets beside a
             velocity law (the other friction law and a cubic power of the velocity), of the same length,
             and again of the length the design says settles the closest pair with probability 0.9
             (`duration_to_settle`, at most 4x): the user following the design's advice. Per truth: how
             often the loop names the truth `identified` on each record.

    python bench/bench_design.py [--seeds 10] [--draws 10] [--tables information,discrimination]
"""
from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.rates import wilson  # noqa: E402
from greyfit.schemas.design import DesignRequest  # noqa: E402
from greyfit.schemas.discovery import DiscoverRequest  # noqa: E402
from greyfit.schemas.fit import FitRequest  # noqa: E402
from greyfit.schemas.simulate import SimulateRequest  # noqa: E402
from greyfit.solvers.design import design_experiment  # noqa: E402
from greyfit.solvers.discovery import discover  # noqa: E402
from greyfit.solvers.fit import fit_model  # noqa: E402
from greyfit.solvers.simulation.simulate import simulate_request  # noqa: E402


def _par(name, value):
    return {"name": name, "value": value, "lower": value / 20, "upper": value * 20}


def mechanical(rng):
    m, k = rng.uniform(0.5, 3), rng.uniform(2, 20)
    c = 2 * rng.uniform(0.2, 0.9) * math.sqrt(k * m)
    wn = math.sqrt(k / m)
    return ({"name": "msd", "states": ["x", "v"], "inputs": ["u"],
             "parameters": [_par("m", m), _par("c", c), _par("k", k)],
             "equations": {"x": "v", "v": "(u - c*v - k*x)/m"}, "outputs": {"y": "x"}},
            {"y": 0.01 / k}, 0.1 / wn, 60 / wn)


def thermal(rng):
    c2, r1, r2 = rng.uniform(5, 20), rng.uniform(0.2, 1.0), rng.uniform(1, 4)
    c1 = rng.uniform(0.5, 2)
    tau = c2 * r2
    return ({"name": "two_node", "states": ["T1", "T2"], "inputs": ["q"],
             "parameters": [{"name": "C1", "value": c1, "fixed": True}, _par("C2", c2), _par("R1", r1), _par("R2", r2)],
             "equations": {"T1": "(q - (T1 - T2)/R1)/C1", "T2": "((T1 - T2)/R1 - T2/R2)/C2"}, "outputs": {"y": "T2"}},
            {"y": 0.005 * r2}, tau / 50, 4 * tau)


def fluid(rng):
    a1, a2 = rng.uniform(0.5, 2), rng.uniform(0.5, 2)
    k1, k2 = rng.uniform(0.2, 1), rng.uniform(0.2, 1)
    tau = max(a1 / k1, a2 / k2)
    return ({"name": "two_tanks", "states": ["h1", "h2"], "inputs": ["q"],
             "parameters": [_par("A1", a1), _par("A2", a2), {"name": "k1", "value": k1, "fixed": True}, _par("k2", k2)],
             "equations": {"h1": "(q - k1*h1)/A1", "h2": "(k1*h1 - k2*h2)/A2"}, "outputs": {"y": "h2"}},
            {"y": 0.005 / k2}, tau / 40, 5 * tau)


FAMILIES = {"mechanical": mechanical, "thermal": thermal, "fluid": fluid}


def _fits(model, experiment, sigma, draws, rng):
    sim = simulate_request(SimulateRequest.model_validate({"model": model, "experiments": [experiment]}))
    y = np.asarray(sim.experiments[0].outputs["y"])
    start = [{**p, "value": p["value"] * (1 if p.get("fixed") else 1.2)} for p in model["parameters"]]
    est = []
    for _ in range(draws):
        noisy = y + sigma * rng.standard_normal(len(y))
        fit = fit_model(FitRequest.model_validate(
            {"model": {**model, "parameters": start}, "experiments": [{**experiment, "outputs": {"y": list(noisy)}}]}))
        est.append([fit.parameters[p["name"]].value for p in model["parameters"] if not p.get("fixed")])
    return np.asarray(est)


def information_row(family: str, seeds: int, draws: int) -> tuple:
    ratios, agreement, wall = [], [], []
    for seed in range(seeds):
        rng = np.random.default_rng(1000 + seed)
        model, outputs, ts, duration = FAMILIES[family](rng)
        n = int(round(duration / ts)) + 1
        times = [round(ts * i, 12) for i in range(n)]
        step = {"name": "step", "time": times, "inputs": {model["inputs"][0]: [1.0] * n},
                "initial_state": {s: 0.0 for s in model["states"]}}
        t0 = time.process_time()
        design = design_experiment(DesignRequest.model_validate(
            {"model": model, "inputs": {model["inputs"][0]: {"lower": 0.0, "upper": 1.0}}, "outputs": outputs,
             "duration": times[-1], "sample_time": ts, "hold": 3 * ts, "baseline": step,
             "options": {"starts": 2, "max_iterations": 100}}))
        wall.append(time.process_time() - t0)
        designed = design.experiment.model_dump()
        spread_d = _fits(model, designed, outputs["y"], draws, rng).std(0, ddof=1)
        spread_s = _fits(model, step, outputs["y"], draws, rng).std(0, ddof=1)
        predicted = np.array([p.stderr for p in design.parameters.values()])
        ratios.append(float(np.max(spread_s / spread_d)))
        agreement += list(predicted / spread_d)
    k = sum(r >= 3 for r in ratios)
    return (family, seeds, float(np.median(ratios)), k, wilson(k, seeds), float(np.median(agreement)),
            float(np.min(agreement)), float(np.max(agreement)), float(np.median(wall)))


def _friction_model(effect: str | None, value: float = 0.0) -> dict:
    extra = {"coulomb": " - Fc*tanh(v/0.02)", "quadratic": " - cq*v*abs(v)", "cubic": " - c3*v^3", None: ""}[effect]
    pars = [{"name": "c", "value": 0.4, "lower": 0.0, "upper": 50},
            {"name": "k", "value": 4.0, "lower": 0.1, "upper": 50}]
    if effect == "coulomb":
        pars.append({"name": "Fc", "value": value, "lower": 0.0, "upper": 10})
    elif effect == "quadratic":
        pars.append({"name": "cq", "value": value, "lower": 0.0, "upper": 10})
    elif effect == "cubic":
        pars.append({"name": "c3", "value": value, "lower": 0.0, "upper": 10})
    return {"name": effect or "msd", "states": ["x", "v"], "inputs": ["u"], "parameters": pars,
            "equations": {"x": "v", "v": "u - c*v - k*x" + extra}, "outputs": {"y": "x"}}


def _named(result, truth: str) -> bool:
    want = {"coulomb": "coulomb", "quadratic": "drag"}[truth]
    return any(want in s.effect and s.verdict == "identified" for s in result.steps)


def _t_design(true_model: dict, rivals: list[str], sizes: dict, duration: float, ts: float, sigma: float):
    return design_experiment(DesignRequest.model_validate(
        {"model": true_model, "criterion": "T",
         "rivals": [{"name": r, "model": _friction_model(r, sizes[r])} for r in rivals],
         "inputs": {"u": {"lower": -0.6, "upper": 0.6}}, "outputs": {"y": sigma}, "duration": duration,
         "sample_time": ts, "hold": 0.25, "options": {"starts": 1}}))


def _named_on(record: dict, true_model: dict, truth: str, sigma: float, rng) -> tuple[bool, bool]:
    sim = simulate_request(SimulateRequest.model_validate({"model": true_model, "experiments": [record]}))
    clean = np.asarray(sim.experiments[0].outputs["y"])
    y = clean + sigma * rng.standard_normal(clean.size)
    result = discover(DiscoverRequest.model_validate(
        {"model": _friction_model(None), "experiments": [{**record, "outputs": {"y": list(y)}}]}))
    return _named(result, truth), bool(result.ambiguous)


def discrimination_row(truth: str, seeds: int) -> tuple:
    """Per seed: the loop on a step record, on the T-optimal record of the same length, and on the
    T-optimal record of the length the design says settles the closest pair with probability 0.9
    (`duration_to_settle`, at most 4x), designed again with it: the user following the design's advice."""
    on_step, on_design, on_advised, ambiguous_step, predicted, lengths = 0, 0, 0, 0, [], []
    for seed in range(seeds):
        rng = np.random.default_rng(2000 + seed)
        sizes = {"coulomb": rng.uniform(0.05, 0.12), "quadratic": rng.uniform(0.3, 0.6), "cubic": 0.5}
        true_model = _friction_model(truth, sizes[truth])
        # the rivals the loop sets beside a velocity law: the other named friction and a power of v
        rivals = [r for r in ("coulomb", "quadratic", "cubic") if r != truth]
        ts, n, sigma = 0.05, 241, 0.005
        duration = ts * (n - 1)
        times = [round(ts * i, 12) for i in range(n)]
        step = {"name": "step", "time": times, "inputs": {"u": [0.6] * n}, "initial_state": {"x": 0.0, "v": 0.0}}
        named, ambiguous = _named_on(step, true_model, truth, sigma, rng)
        on_step += named
        ambiguous_step += ambiguous
        design = _t_design(true_model, rivals, sizes, duration, ts, sigma)
        on_design += _named_on(design.experiment.model_dump(), true_model, truth, sigma, rng)[0]
        closest = min(design.discrimination, key=lambda d: d.expected_delta_bic)
        if closest.duration_to_settle is not None:
            longer = round(min(closest.duration_to_settle, 4 * duration) / 0.25) * 0.25   # whole holds
            design = _t_design(true_model, rivals, sizes, max(longer, duration), ts, sigma)
            closest = min(design.discrimination, key=lambda d: d.expected_delta_bic)
        predicted.append(closest.settle_probability or 0.0)
        lengths.append(design.experiment.time[-1])
        named_advised = _named_on(design.experiment.model_dump(), true_model, truth, sigma, rng)[0]
        on_advised += named_advised
        print(f"  {truth} seed {seed}: step {named}, designed {duration:.0f} s, advised "
              f"{lengths[-1]:.1f} s (P {predicted[-1]:.2f}) named {named_advised}", file=sys.stderr, flush=True)
    return (truth, seeds, on_step, ambiguous_step, on_design, on_advised, wilson(on_advised, seeds),
            float(np.mean(predicted)), float(np.median(lengths)))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--draws", type=int, default=10)
    ap.add_argument("--tables", default="information,discrimination")
    ap.add_argument("--families", default=",".join(FAMILIES))
    ap.add_argument("--truths", default="coulomb,quadratic", help="the discrimination table's rows")
    args = ap.parse_args()
    tables = args.tables.split(",")
    if "information" in tables:
        print("| family | systems | median worst spread ratio (step/design) | ≥ 3× | 95 % CI | predicted/MC spread "
              "median [min, max] | design CPU s |")
        print("|---|---|---|---|---|---|---|")
        for family in args.families.split(","):
            f, n, med, k, (lo, hi), ag, agmin, agmax, wall = information_row(family, args.seeds, args.draws)
            print(f"| {f} | {n} | {med:.1f} | {k}/{n} | {lo:.2f}-{hi:.2f} | {ag:.2f} [{agmin:.2f}, {agmax:.2f}] "
                  f"| {wall:.1f} |", flush=True)
    if "discrimination" in tables:
        print("\n| truth | seeds | named on the step record | ambiguous there | named on the designed record "
              "(same length) | named on the advised length | 95 % CI | predicted P(settled), mean | median length s |")
        print("|---|---|---|---|---|---|---|---|---|")
        for truth in args.truths.split(","):
            t, n, s, amb, d, a, (lo, hi), p, length = discrimination_row(truth, args.seeds)
            print(f"| {t} | {n} | {s}/{n} | {amb}/{n} | {d}/{n} | {a}/{n} | {lo:.2f}-{hi:.2f} | {p:.2f} "
                  f"| {length:.1f} |", flush=True)


if __name__ == "__main__":
    main()
