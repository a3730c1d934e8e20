"""The discovery loop on a coarsely sampled two-lag process with a transport delay, over many seeds.

Truth (tests/shape_systems.py, simulated with scipy): K/(τ1 s + 1)/(τ2 s + 1) with τ1 = 15 s, τ2 = 4 s,
K = 2, the input a held random staircase acting 4 samples late, sampled at 1 s, 2 000 samples,
position-like output with 1 % noise (white, or AR(1) ρ 0.8 with `--kinds white,ar1`); the model is
declared without the delay, its second lag started at 1 s. Each seed draws another staircase and
another noise; the validation record is another seed's.

Per run it prints the delay found (the input the final model reads, matched against u shifted by
0-24 samples), the lags' and the gain's relative errors, whether the run passes (the right delay,
both lags and K within 5 %), and CPU and wall seconds of the discovery; then the pass rate, and the
medians. The load average is printed before and after.

    OPENBLAS_NUM_THREADS=1 python bench/bench_discovery_delay.py [--seeds 10] [--kinds white]
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from greyfit.schemas.discovery import DiscoverRequest  # noqa: E402
from greyfit.solvers.discovery import discover  # noqa: E402
from tests import shape_systems as ss  # noqa: E402

TOLERANCE = 0.05


def body_of(seed: int, kind: str) -> dict:
    model = ss.delay_model()
    model["parameters"][2]["value"] = 1.0   # the second lag collapsed, as the test starts it
    # a generous wall budget: the bench measures what the search finds, not the machine's load
    return {"model": model, "method": "multiple_shooting", "options": {"input_interpolation": "zoh"},
            "discovery": {"time_budget_s": 3600.0},
            "experiments": [ss.delay_record(seed, kind=kind)],
            "validation": [ss.delay_record(seed + 100, kind=kind, name="val")]}


def shift_read(body: dict, res) -> int | None:
    """Samples by which the input the final model reads lags u (None when no input was added)."""
    name = res.model.inputs[-1]
    read = res.added_inputs.get("est", {}).get(name)
    if read is None:
        return 0 if not res.steps else None
    u = np.array(body["experiments"][0]["inputs"]["u"])
    read = np.array(read)
    return int(np.argmin([np.abs(read[30:] - np.roll(u, s)[30:]).max() for s in range(25)]))


def run(seed: int, kind: str) -> dict:
    body = body_of(seed, kind)
    c0, w0 = time.process_time(), time.perf_counter()
    res = discover(DiscoverRequest.model_validate(body))
    cpu, wall = time.process_time() - c0, time.perf_counter() - w0
    p = res.fit.parameters
    taus = sorted([p["tau1"].value, p["tau2"].value])
    truth = sorted([ss.DELAY["tau1"], ss.DELAY["tau2"]])
    errs = {"tau_a": abs(taus[0] / truth[0] - 1), "tau_b": abs(taus[1] / truth[1] - 1),
            "K": abs(p["K"].value / ss.DELAY["K"] - 1)}
    shift = shift_read(body, res)
    only_delays = bool(res.steps) and all(s.effect == "input_delay" for s in res.steps)
    ok = only_delays and shift == ss.DELAY["delay_samples"] and max(errs.values()) <= TOLERANCE
    return {"seed": seed, "kind": kind, "shift": shift, "steps": len(res.steps), "ok": ok, "cpu": cpu,
            "wall": wall, **errs}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--kinds", default="white")
    args = ap.parse_args()
    print(f"load average before: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    print("| noise | seed | delay found | steps | τ (4 s) err | τ (15 s) err | K err | pass | CPU s | wall s |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    runs = []
    for kind in args.kinds.split(","):
        for seed in range(1, args.seeds + 1):
            r = run(seed, kind)
            runs.append(r)
            print(f"| {kind} | {seed} | {r['shift']} | {r['steps']} | {100 * r['tau_a']:.2f} % | "
                  f"{100 * r['tau_b']:.2f} % | {100 * r['K']:.2f} % | {'yes' if r['ok'] else 'no'} | "
                  f"{r['cpu']:.1f} | {r['wall']:.1f} |", flush=True)
    for kind in args.kinds.split(","):
        mine = [r for r in runs if r["kind"] == kind]
        print(f"{kind}: passed {sum(r['ok'] for r in mine)} of {len(mine)} (right delay "
              f"{sum(r['shift'] == ss.DELAY['delay_samples'] for r in mine)}); median CPU "
              f"{np.median([r['cpu'] for r in mine]):.1f} s, wall {np.median([r['wall'] for r in mine]):.1f} s")
    print(f"load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
