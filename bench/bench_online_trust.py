"""Monte Carlo of the online estimators' verdict on random plants (tests/online_generator.py).

Rows: a plant kind, an input, an estimator (recursive least squares at its defaults, MRAS at its
defaults), over --seeds random plants and records. Columns: the share called `good` (95 % Wilson
interval), the share called `good` with a parameter more than 10 % off (it must be 0), the share
with every parameter within 10 %, the share said not persistently exciting (`poor_excitation`;
it must be 100 % where the input's order is below what the model needs and 0 % where it is not),
and the share said not settled (`estimate_not_settled`).

    python bench/bench_online_trust.py [--seeds 20] [--rows rl:rich:rls,...]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.rates import share  # noqa: E402
from greyfit.schemas import FitRequest  # noqa: E402
from greyfit.solvers.fit import fit_model  # noqa: E402
from tests.online_generator import random_case  # noqa: E402

METHODS = {"rls": "recursive_least_squares", "mras": "mras"}
ROWS = ["rl:rich:rls", "rl:rich:mras", "first:rich:rls", "first:rich:mras", "rlc:rich:rls", "rlc:rich:mras",
        "second:rich:rls", "second:rich:mras", "rl:dc:rls", "first:dc:rls", "rlc:one_sine:rls",
        "rlc:two_sines:rls", "second:one_sine:rls", "second:two_sines:rls"]


def run(system: str, inputs: str, method: str, seeds: int) -> dict:
    row = {"n": 0, "good": 0, "good_off": 0, "within": 0, "pe": 0, "unsettled": 0}
    for seed in range(seeds):
        case = random_case(system, inputs, seed)
        res = fit_model(FitRequest.model_validate({**case.body, "method": METHODS[method]}))
        codes = {w.code for w in res.warnings}
        within = all(abs(res.parameters[k].value / v - 1) <= 0.1 for k, v in case.truth.items())
        row["n"] += 1
        row["good"] += res.quality == "good"
        row["good_off"] += res.quality == "good" and not within
        row["within"] += within
        row["pe"] += "poor_excitation" in codes
        row["unsettled"] += "estimate_not_settled" in codes
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--rows", default=",".join(ROWS))
    args = ap.parse_args()
    print("| plant | input | estimator | `good` | `good` and > 10 % off | all within 10 % | not exciting "
          "| not settled |")
    print("|---|---|---|---|---|---|---|---|")
    for spec in args.rows.split(","):
        system, inputs, method = spec.split(":")
        r = run(system, inputs, method, args.seeds)
        n = r["n"]
        print(f"| {system} | {inputs} | {method} | {share(r['good'], n)} | {share(r['good_off'], n)} | "
              f"{share(r['within'], n)} | {share(r['pe'], n)} | {share(r['unsettled'], n)} |", flush=True)


if __name__ == "__main__":
    main()
