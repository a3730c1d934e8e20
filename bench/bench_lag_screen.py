"""How often the lack-of-fit screen sees an unmodelled first-order lag (docs/discovery-loop.md).

Systems of tests/lag_systems.py (an RL circuit measured by its current, a mass-spring-damper by its
position, two thermal nodes by both temperatures), each with a held random binary input, 400
samples, white noise of 1 % of the output's spread, and a random lag the model lacks: on the
sensor, on the input, or between the thermal nodes, of 0.5-4 sample intervals. Per row and --seeds
records: the share of output-error fits (defaults) flagged `missing_effect_likely` with a lag among
the named effects, the share called `good`, and on the right model the false-alarm share.

    python bench/bench_lag_screen.py [--seeds 20]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.rates import share  # noqa: E402
from greyfit.schemas.fit import FitRequest  # noqa: E402
from greyfit.solvers.fit import fit_model  # noqa: E402
from tests.lag_systems import declared, lag_record  # noqa: E402

LAGS = {"sensor_lag", "input_lag", "extra_pole"}
ROWS = [("rl", "none"), ("rl", "sensor"), ("rl", "input"), ("msd", "none"), ("msd", "sensor"), ("msd", "input"),
        ("thermal", "none"), ("thermal", "sensor"), ("thermal", "pole")]


def run(system: str, lag: str, seeds: int) -> dict:
    row = {"n": 0, "named": 0, "flagged": 0, "good": 0}
    for seed in range(seeds):
        tau = float(np.random.default_rng(seed + 7).uniform(0.5, 4.0))
        res = fit_model(FitRequest.model_validate({"model": declared(system),
                                                   "experiments": [lag_record(system, lag, tau, seed)]}))
        named = {c["effect"] for w in res.warnings if w.code == "missing_effect_likely" for c in w.detail["candidates"]}
        row["n"] += 1
        row["flagged"] += bool(named)
        row["named"] += bool(named & LAGS)
        row["good"] += res.quality == "good"
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    args = ap.parse_args()
    print("| system | lag the model lacks | `missing_effect_likely` | a lag named | `good` |")
    print("|---|---|---|---|---|")
    for system, lag in ROWS:
        r = run(system, lag, args.seeds)
        print(f"| {system} | {lag} | {share(r['flagged'], r['n'])} | {share(r['named'], r['n'])} | "
              f"{share(r['good'], r['n'])} |", flush=True)


if __name__ == "__main__":
    main()
