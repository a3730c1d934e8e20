"""Monte Carlo of the frequency fits' verdict on random systems (tests/frequency_generator.py).

Per misspecification (right, missing_pole, missing_zero, delay) over --seeds random plants: the share
of fits called `good` (95 % Wilson interval), the share where the trend test (`missing_effect_likely`)
fired, and, among the fits whose error moves some estimate by more than 3 standard errors, the share
called `good` (it must be 0). Coverage: the share of right-model fits whose 95 % intervals hold every
true parameter.

    python bench/bench_frequency_trust.py [--seeds 25]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.rates import share  # noqa: E402
from greyfit.schemas.frequency import FrequencyFitRequest  # noqa: E402
from greyfit.solvers.frequency import fit_frequency_response  # noqa: E402
from tests.frequency_generator import KINDS, random_case  # noqa: E402


def run(kind: str, seeds: int) -> dict:
    row = {"n": 0, "good": 0, "trend": 0, "moved": 0, "moved_good": 0, "covered": 0}
    for seed in range(seeds):
        case = random_case(seed, kind)
        res = fit_frequency_response(FrequencyFitRequest.model_validate(case.body))
        est = res.parameters
        sds = [abs(est[k].value - v) / est[k].stderr for k, v in case.truth.items() if est[k].stderr]
        row["n"] += 1
        row["good"] += res.quality == "good"
        row["trend"] += any(w.code == "missing_effect_likely" for w in res.warnings)
        moved = bool(sds) and max(sds) > 3.0
        row["moved"] += moved
        row["moved_good"] += moved and res.quality == "good"
        row["covered"] += all(est[k].ci95 is not None and est[k].ci95[0] <= v <= est[k].ci95[1]
                              for k, v in case.truth.items())
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=25)
    args = ap.parse_args()
    print("| truth beyond the model | `good` | trend test fired | moved > 3 sd: `good` "
          "| all true values in the 95 % intervals |")
    print("|---|---|---|---|---|")
    for kind in KINDS:
        r = run(kind, args.seeds)
        print(f"| {kind} | {share(r['good'], r['n'])} | {share(r['trend'], r['n'])} | "
              f"{share(r['moved_good'], r['moved'])} | {share(r['covered'], r['n'])} |", flush=True)


if __name__ == "__main__":
    main()
