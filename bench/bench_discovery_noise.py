"""False positives of the discovery loop under coloured measurement noise.

Complete models (nothing is missing) measured in position only: a mass-spring-damper and a Duffing
oscillator with its cubic spring declared, noise 1 % of the position's spread that is white, a
first-order low-pass at 0.15 of Nyquist (lag-1 correlation 0.62) or AR(1) with coefficient 0.9,
many seeds. Prints per (system, noise):

- `loop FP`: runs where discovery added anything (the rate users see; nominal: at most
  `significance`, 0.01, family-wise);
- `screen FP`: runs whose first screen flagged any candidate significant (Bonferroni over the
  ~100-150 library candidates: also nominally ≤ 0.01; the confirming refit is the second gate);
- `fixed 5 % / 1 %`: the fraction of single, unselected candidates (cubic spring, quadratic drag,
  offset, sensor offset and gain) with screening p below 0.05 / 0.01 — the calibration of the score
  test itself (nominal 0.05 / 0.01);
- `refit p < 1e-3`: of the refits tried, the fraction whose likelihood-ratio test on the effective
  sample size would pass at 1e-3 (the loop needs the Bonferroni level, ~1e-5).

    OPENBLAS_NUM_THREADS=1 python bench/bench_discovery_noise.py [--seeds 30] [--kinds white,lowpass,ar1]
    OPENBLAS_NUM_THREADS=1 python bench/bench_discovery_noise.py --library [--seeds 10]

`--library`: the complete models of the wider library instead (tests/discovery_systems.py `COMPLETE`:
the heated block with its radiation declared, the oscillator with its μy²ẏ damping, the RLC circuit
with its sensor offset; 500 samples, AR(1) noise ρ 0.8, inputs held and declared `zoh`, multiple
shooting, as tests/solvers/test_discovery_library.py runs two seeds of them): per system the runs
where anything was added, with its 95 % Wilson interval, and what was added.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench.rates import share  # noqa: E402
from greyfit.schemas.discovery import DiscoverRequest  # noqa: E402
from greyfit.solvers.discovery import confirm, discover  # noqa: E402
from tests import coloured_records as cr  # noqa: E402
from tests import discovery_systems as ds  # noqa: E402

FIXED = {"cubic_stiffness", "quadratic_drag", "offset", "output_offset", "output_gain"}


def record(system: str, seed: int, kind: str, n: int | None) -> tuple[dict, dict]:
    if system == "msd":
        return cr.msd_position_model(), cr.msd_record(n or 1001, seed, kind)
    return cr.duffing_complete_model(), cr.duffing_record(n or 801, seed, kind)


def library_rows(seeds: int) -> None:
    """Runs of `discover` on the wider library's complete models that added anything, per system."""
    print(f"{'system':10} {'runs where a term was added':>30}  {'s/run':>5}  added")
    for system, (model, record) in sorted(ds.COMPLETE.items()):
        added: dict[str, int] = {}
        runs_added = 0
        t0 = time.perf_counter()
        for seed in range(seeds):
            res = discover(DiscoverRequest.model_validate({
                "model": model, "experiments": [record(seed)], "method": "multiple_shooting",
                "options": {"input_interpolation": "zoh"}}))
            runs_added += bool(res.steps)
            for s in res.steps:
                added[s.effect] = added.get(s.effect, 0) + 1
        print(f"{system:10} {share(runs_added, seeds):>30}  {(time.perf_counter() - t0) / seeds:5.1f}  "
              f"{', '.join(f'{k}×{v}' for k, v in added.items()) or '-'}", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=30)
    ap.add_argument("--kinds", default="white,lowpass,ar1")
    ap.add_argument("--systems", default="msd,duffing")
    ap.add_argument("--samples", type=int, default=None, help="record length (default 1001 MSD, 801 Duffing)")
    ap.add_argument("--library", action="store_true", help="the wider library's complete models instead")
    args = ap.parse_args()
    if args.library:
        library_rows(args.seeds)
        return

    screens: list = []
    real_screen = confirm.screen

    def capture(*a, **k):
        out = real_screen(*a, **k)
        screens.append(out)
        return out
    confirm.screen = capture
    refit_ps: list[float] = []
    real_lr = confirm.refit_likelihood_ratio

    def capture_lr(*a, **k):
        out = real_lr(*a, **k)
        if out[1] is not None:
            refit_ps.append(out[1])
        return out
    confirm.refit_likelihood_ratio = capture_lr

    rows = []
    for kind in args.kinds.split(","):
        for system in args.systems.split(","):
            loop_fp = screen_fp = 0
            fixed_p: list[float] = []
            refit_ps.clear()
            added: dict[str, int] = {}
            t0 = time.perf_counter()
            for seed in range(args.seeds):
                screens.clear()
                model, exp = record(system, seed, kind, args.samples)
                res = discover(DiscoverRequest.model_validate({"model": model, "experiments": [exp],
                                                               "method": "multiple_shooting"}))
                if res.steps:
                    loop_fp += 1
                    for s in res.steps:
                        added[s.effect] = added.get(s.effect, 0) + 1
                if screens:
                    first = screens[0]
                    screen_fp += any(sc.significant for sc in first.scored)
                    seen = set()
                    for sc in first.scored:
                        if sc.candidate.effect in FIXED and sc.scored_on == "outputs" and sc.candidate.key not in seen:
                            seen.add(sc.candidate.key)
                            fixed_p.append(sc.score.p_value)
            fp = np.array(fixed_p)
            rows.append((system, kind, cr.lag1(kind), args.seeds, loop_fp, screen_fp,
                         float(np.mean(fp < 0.05)) if fp.size else float("nan"),
                         float(np.mean(fp < 0.01)) if fp.size else float("nan"), fp.size,
                         len(refit_ps), float(np.mean(np.array(refit_ps) < 1e-3)) if refit_ps else float("nan"),
                         ", ".join(f"{k}×{v}" for k, v in added.items()) or "-",
                         (time.perf_counter() - t0) / args.seeds))
            print_rows(rows[-1:], header=len(rows) == 1)
    print("\nnominal: loop and screen FP ≤ 1 % of runs (significance 0.01, family-wise); fixed 0.05 / 0.01")


def print_rows(rows, header: bool) -> None:
    if header:
        print(f"{'system':8} {'noise':8} {'lag-1':>5} {'runs':>4} {'loop FP':>8} {'screen FP':>9} "
              f"{'fixed 5%':>8} {'fixed 1%':>8} {'(n)':>5} {'refits':>6} {'p<1e-3':>6}  {'s/run':>5}  added")
    for (system, kind, rho, runs, loop_fp, screen_fp, f5, f1, nf, nrefit, r3, added, per) in rows:
        print(f"{system:8} {kind:8} {rho:5.2f} {runs:4d} {loop_fp:4d} ({100 * loop_fp / runs:3.0f}%) "
              f"{screen_fp:3d} ({100 * screen_fp / runs:3.0f}%) {f5:8.3f} {f1:8.3f} {nf:5d} {nrefit:6d} "
              f"{r3:6.2f}  {per:5.1f}  {added}", flush=True)


if __name__ == "__main__":
    main()
