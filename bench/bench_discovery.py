"""Discovery speed on position-only records (issue #11's loop target: ≤ 10 s at 2 000–4 000 samples).

Records: a Duffing oscillator declared without its cubic spring (k3 = 3) and a mass-spring-damper
declared without its Coulomb friction (Fc = 0.5 N, tanh(v/1e-3)), position measured with 1 % noise,
a second record for validation, multiple shooting. Prints per record the wall time of each phase of
`discover` (`DiscoveryResult.timings`), the total, the effect found and the parameters, and as the
peer the fit of the true model from the same declared start (what a user who already knew the
effect pays): `x oracle` is discovery's total over that fit.

    OPENBLAS_NUM_THREADS=1 python bench/bench_discovery.py [--samples 2000,4000] [--baseline ../main]
    OPENBLAS_NUM_THREADS=1 python bench/bench_discovery.py --library [--seeds 10]

`--library`: the wider library's laws over many seeds (tests/discovery_systems.py: radiative loss of
a heated block, damping μy²ẏ, an Arrhenius rate, a sensor offset beside a source offset; outputs
only, 1 % AR(1) noise, held inputs, a validation record): per law, how often the right law is the
one step added (recall), how often what was added is right (precision), spurious terms, ambiguous
verdicts, the median declared-parameter error and the median time. Measured (10 seeds, a loaded
2-core machine, load average 10-15):

    law            seeds recall precis  spur ambig  par err   time
    radiation         10    90%    90%     1     0     0.1%  14.1s  (worst parameter error 9.5 %)
    power_law         10   100%   100%     0     0     0.9%   2.9s  (worst parameter error 2.2 %)
    arrhenius         10   100%   100%     0     0     0.0%  19.5s  (worst parameter error 0.0 %)
    output_offset     10   100%   100%     0     0     0.1%  11.5s  (worst parameter error 0.1 %)

`--baseline CHECKOUT` also runs each request through another checkout's `discover` (e.g. the main
branch, before this loop's warm starts and width refinement), in a subprocess, on the same data.

Small matrices: a second BLAS thread only contends with the solver on a loaded 2-core machine
(measured: a 4000×200 projection 12 ms single-threaded, 270 ms with 2 threads under load).
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from greyfit.schemas.discovery import DiscoverRequest  # noqa: E402
from greyfit.schemas.fit import FitRequest  # noqa: E402
from greyfit.solvers.discovery import discover  # noqa: E402
from greyfit.solvers.fit import fit_model  # noqa: E402
from tests import coloured_records as cr  # noqa: E402
from tests import partial_systems as ps  # noqa: E402

FC = 0.5
TRUTH = {"duffing": {"d": 0.4, "k": 2.0, "k3": 3.0}, "coulomb_msd": {"c": 0.8, "k": 5.0, "Fc": FC}}


def coulomb(x, v):
    return FC * np.tanh(v / 1e-3)


def case(name: str, n: int) -> tuple[dict, dict]:
    """(discovery request body, true model) of a record."""
    if name == "duffing":
        body = {"model": ps.duffing_model(), "experiments": [cr.duffing_record(n, 1, name="est")],
                "validation": [cr.duffing_record(n // 2, 51, name="val")]}
        true = ps.duffing_model()
        true["parameters"].append({"name": "k3", "value": 1.0})
        true["equations"]["yd"] = "(u - d*yd - k*y - k3*y^3)/m"
    else:
        body = {"model": cr.msd_position_model(),
                "experiments": [cr.msd_record(n, 1, extra_force=coulomb, name="est")],
                "validation": [cr.msd_record(n // 2, 51, extra_force=coulomb, name="val", x0=(-0.2, 0.1),
                                             t0=n * 0.02)]}
        true = cr.msd_position_model()
        true["parameters"].append({"name": "Fc", "value": 0.1, "lower": 0.0})
        true["equations"]["v"] = "(u - c*v - k*x - Fc*tanh(v/0.001))/m"
    return {**body, "method": "multiple_shooting"}, true


BASELINE = """
import json, sys, time
sys.path.insert(0, sys.argv[1])
from greyfit.schemas.discovery import DiscoverRequest
from greyfit.solvers.discovery import discover
body = json.load(sys.stdin)
t0 = time.perf_counter()
res = discover(DiscoverRequest.model_validate(body))
print(json.dumps({"total": time.perf_counter() - t0, "effects": [s.effect for s in res.steps],
                  "params": {k: v.value for k, v in res.fit.parameters.items() if not v.fixed}}))
"""


def run_baseline(checkout: str, body: dict) -> str:
    out = subprocess.run([sys.executable, "-c", BASELINE, checkout],
                         input=json.dumps(body), capture_output=True, text=True, env=dict(os.environ))
    try:
        res = json.loads(out.stdout.strip().splitlines()[-1])
    except (IndexError, json.JSONDecodeError):
        return "baseline failed: " + out.stderr.strip().splitlines()[-1][:100] if out.stderr.strip() else "?"
    params = ", ".join(f"{k}={v:.4g}" for k, v in res["params"].items())
    return f"baseline {res['total']:.1f} s: {'+'.join(res['effects']) or 'nothing'}; {params}"


def library_case(name: str, seed: int) -> tuple[dict, str, dict[str, float]]:
    """(request body, the law that is missing, declared parameters' truth) of one seed."""
    from tests import discovery_systems as ds
    cases = {
        "radiation": (ds.block_model, ds.block_record, {"C": ds.BLOCK["C"], "h": ds.BLOCK["h"]}),
        "power_law": (ds.amplitude_damping_model, ds.amplitude_damping_record, {"c": ds.VDP["c"], "k": ds.VDP["k"]}),
        "arrhenius": (ds.reactor_model, ds.reactor_record, {"h": ds.REACTOR["h"]}),
        "output_offset": (ds.rlc_model, ds.rlc_record, {n: ds.RLC[n] for n in ("L", "R", "C")}),
    }
    model, record, truth = cases[name]
    body = {"model": model(), "experiments": [record(seed, rho=0.5)],
            "validation": [record(seed + 100, rho=0.5, name="val")], "method": "multiple_shooting",
            "options": {"input_interpolation": "zoh"}}
    return body, name, truth


def library_rates(seeds: int) -> None:
    print(f"{'law':14} {'seeds':>5} {'recall':>6} {'precis':>6} {'spur':>5} {'ambig':>5} {'par err':>8} {'time':>6}")
    for name in ("radiation", "power_law", "arrhenius", "output_offset"):
        hits, added, spurious, ambiguous, errs, times = 0, 0, 0, 0, [], []
        for seed in range(seeds):
            body, law, truth = library_case(name, seed)
            t0 = time.perf_counter()
            res = discover(DiscoverRequest.model_validate(body))
            times.append(time.perf_counter() - t0)
            effects = [s.effect for s in res.steps]
            hits += effects[:1] == [law]
            added += len(effects)
            spurious += sum(e != law for e in effects)
            ambiguous += any(s.verdict == "ambiguous" for s in res.steps)
            errs.append(max(abs(res.fit.parameters[k].value / v - 1) for k, v in truth.items()))
        print(f"{name:14} {seeds:5d} {hits / seeds:6.0%} {(added - spurious) / max(added, 1):6.0%} {spurious:5d} "
              f"{ambiguous:5d} {100 * float(np.median(errs)):7.1f}% {float(np.median(times)):5.1f}s"
              f"  (worst parameter error {100 * max(errs):.1f} %)", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--samples", default="2000,4000")
    ap.add_argument("--records", default="duffing,coulomb_msd")
    ap.add_argument("--baseline", default=None, help="another checkout to run the same requests through")
    ap.add_argument("--library", action="store_true", help="the wider library's laws over many seeds")
    ap.add_argument("--seeds", type=int, default=10)
    args = ap.parse_args()
    if args.library:
        library_rates(args.seeds)
        return
    print(f"{'record':12} {'samples':>7} {'base':>6} {'screen':>6} {'refits':>6} {'valid':>6} {'other':>6} "
          f"{'total':>6} {'oracle':>6} {'x oracle':>8}  effect found; parameters (truth)")
    for name in args.records.split(","):
        for n in (int(s) for s in args.samples.split(",")):
            body, true = case(name, n)
            t0 = time.perf_counter()
            res = discover(DiscoverRequest.model_validate(body))
            total = time.perf_counter() - t0
            # the peer: the true model fitted from the declared start; the true tanh(v/1e-3) needs
            # 4 RK4 substeps at 50 Hz (|λ|h = Fc/(m ε) h/4 ≤ 1.5, as the loop's rule)
            opts = {"substeps": 4 if name == "coulomb_msd" else 1}
            t0 = time.perf_counter()
            fit_model(FitRequest.model_validate({**{k: v for k, v in body.items() if k != "validation"},
                                                 "model": true, "options": opts}))
            oracle = time.perf_counter() - t0
            tm = res.timings
            found = ", ".join(f"{s.effect} ({s.term})" for s in res.steps) or res.conclusion[:60]
            params = ", ".join(f"{k}={v.value:.4g}" for k, v in res.fit.parameters.items() if not v.fixed)
            truth = ", ".join(f"{k}={v:g}" for k, v in TRUTH[name].items())
            print(f"{name:12} {n:7d} {tm['base_fit']:6.2f} {tm['screening']:6.2f} {tm['refits']:6.2f} "
                  f"{tm['validation']:6.2f} {tm['other']:6.2f} {total:6.2f} {oracle:6.2f} {total / oracle:8.1f}  "
                  f"{found}; {params} ({truth}){' [budget]' if res.budget_exhausted else ''}", flush=True)
            if args.baseline:
                print(f"{'':12} {'':7} {run_baseline(args.baseline, body)}", flush=True)


if __name__ == "__main__":
    main()
