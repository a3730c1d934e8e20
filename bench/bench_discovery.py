"""Discovery speed on position-only records (the target: a 2 000-4 000-sample, 2-4-state discovery
in well under 30 s), and the must-show cases' rates over many seeds (`--library`).

Records: a Duffing oscillator declared without its cubic spring (k3 = 3) and a mass-spring-damper
declared without its Coulomb friction (Fc = 0.5 N, tanh(v/1e-3)), position measured with 1 % noise,
a second record for validation, multiple shooting. Prints per record the wall time of each phase of
`discover` (`DiscoveryResult.timings`), the total wall and CPU seconds with the load average before
and after (wall time on a shared machine is mostly waiting), the effect found and the parameters,
and as the peer (`oracle`) the wall time of fitting the true model from the same declared start
(what a user who already knew the effect pays).

    OPENBLAS_NUM_THREADS=1 python bench/bench_discovery.py [--samples 2000,4000] [--baseline ../main]
    OPENBLAS_NUM_THREADS=1 python bench/bench_discovery.py --library [--seeds 10]

`--library`: discovery's must-show cases over many seeds (tests/discovery_systems.py: radiative loss
of a heated block, damping μy²ẏ, an Arrhenius rate, a sensor offset beside a source offset, the same
measured on vc alone where the two are equivalent; outputs only, 1 % AR(1) noise, held inputs, a
validation record; and tests/shape_systems.py's hysteretic isolator, which must end `unexplained`
with nothing named). Per case: how often the right answer is the whole result (recall: the right law
is the one step, or for the vc-only RLC either offset with `ambiguous`, or for the hysteresis nothing
named and `unexplained`), how often what was added is right (precision), spurious terms, `ambiguous`
and `approximates` verdicts, runs ending `unexplained`, what was named, the median and worst
declared-parameter error, and the median and worst CPU seconds (wall seconds depend on the load).
The table it prints is in docs/discovery.md.

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
    from tests import shape_systems as ss
    if name == "hysteresis":
        body = {"model": ss.bouc_wen_model(), "experiments": [ss.bouc_wen_record(seed)],
                "validation": [ss.bouc_wen_record(seed + 100, name="val")], "method": "multiple_shooting"}
        return body, "", {}
    cases = {
        "radiation": (ds.block_model, ds.block_record, {"C": ds.BLOCK["C"], "h": ds.BLOCK["h"]}),
        "power_law": (ds.amplitude_damping_model, ds.amplitude_damping_record, {"c": ds.VDP["c"], "k": ds.VDP["k"]}),
        "arrhenius": (ds.reactor_model, ds.reactor_record, {"h": ds.REACTOR["h"]}),
        "output_offset": (ds.rlc_model, ds.rlc_record, {n: ds.RLC[n] for n in ("L", "R", "C")}),
        "offsets_vc_only": (ds.rlc_model, ds.rlc_record, {n: ds.RLC[n] for n in ("L", "R", "C")}),
    }
    model, record, truth = cases[name]
    body = {"model": model(), "experiments": [record(seed, rho=0.5)],
            "validation": [record(seed + 100, rho=0.5, name="val")], "method": "multiple_shooting",
            "options": {"input_interpolation": "zoh"}}
    if name == "offsets_vc_only":   # a sensor offset and a source offset are equivalent on vc alone
        body["model"]["outputs"] = {"vc": "vc"}
        for rec in (*body["experiments"], *body["validation"]):
            rec["outputs"] = {"vc": rec["outputs"]["vc"]}
        return body, "output_offset|offset", truth
    return body, name, truth


LIBRARY_CASES = ("radiation", "power_law", "arrhenius", "output_offset", "offsets_vc_only", "hysteresis")


def right_answer(law: str, res) -> bool:
    """Whether a discovery result is the case's right answer (see the module docstring)."""
    effects = [s.effect for s in res.steps]
    if not law:   # hysteresis: nothing named, said to be unexplained
        return not effects and res.unexplained is not None
    if "|" in law:   # either of two equivalent laws, said to be ambiguous with the other
        return len(effects) == 1 and effects[0] in law.split("|") and res.ambiguous
    return effects == [law]


def library_rates(seeds: int, names: list[str]) -> None:
    from collections import Counter
    print(f"load average at the start: {os.getloadavg()[0]:.1f}", flush=True)
    print("| case | seeds | recall | precision | spurious | ambiguous | approximates | unexplained | named "
          "| param err median (worst) | CPU s median (worst) | wall s median |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    for name in names:
        hits, added, spurious, ambiguous, approx, unexpl, errs, cpus, walls = 0, 0, 0, 0, 0, 0, [], [], []
        named: Counter = Counter()
        for seed in range(seeds):
            body, law, truth = library_case(name, seed)
            t0, c0 = time.perf_counter(), time.process_time()
            res = discover(DiscoverRequest.model_validate(body))
            walls.append(time.perf_counter() - t0)
            cpus.append(time.process_time() - c0)
            effects = [s.effect for s in res.steps]
            named.update(effects or ["nothing"])
            hits += right_answer(law, res)
            added += len(effects)
            spurious += sum(e not in law.split("|") for e in effects)
            ambiguous += any(s.verdict == "ambiguous" for s in res.steps)
            approx += any(s.verdict == "approximates" for s in res.steps)
            unexpl += res.unexplained is not None
            if truth:
                errs.append(max(abs(res.fit.parameters[k].value / v - 1) for k, v in truth.items()))
        err = f"{100 * float(np.median(errs)):.1f} % ({100 * max(errs):.1f} %)" if errs else "n/a"
        shown = ", ".join(f"{k} {v}" for k, v in named.most_common())
        precision = f"{(added - spurious) / added:.0%}" if added else "n/a"
        print(f"| {name} | {seeds} | {hits / seeds:.0%} | {precision} | {spurious} | {ambiguous} | {approx} | "
              f"{unexpl} | {shown} | {err} | {float(np.median(cpus)):.1f} ({max(cpus):.1f}) | "
              f"{float(np.median(walls)):.1f} |", flush=True)
    print(f"load average at the end: {os.getloadavg()[0]:.1f}", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--samples", default="2000,4000")
    ap.add_argument("--records", default="duffing,coulomb_msd")
    ap.add_argument("--baseline", default=None, help="another checkout to run the same requests through")
    ap.add_argument("--library", action="store_true", help="the must-show cases over many seeds")
    ap.add_argument("--cases", default=",".join(LIBRARY_CASES), help="with --library: which cases")
    ap.add_argument("--seeds", type=int, default=10)
    args = ap.parse_args()
    if args.library:
        library_rates(args.seeds, args.cases.split(","))
        return
    print(f"{'record':12} {'samples':>7} {'base':>6} {'shape':>6} {'screen':>6} {'refits':>6} {'valid':>6} "
          f"{'other':>6} {'wall':>6} {'CPU':>6} {'load':>9} {'oracle':>6}  effect found; parameters (truth)")
    for name in args.records.split(","):
        for n in (int(s) for s in args.samples.split(",")):
            body, true = case(name, n)
            load0 = os.getloadavg()[0]
            t0, c0 = time.perf_counter(), time.process_time()
            res = discover(DiscoverRequest.model_validate(body))
            total, cpu = time.perf_counter() - t0, time.process_time() - c0
            load = f"{load0:.1f}-{os.getloadavg()[0]:.1f}"
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
            print(f"{name:12} {n:7d} {tm['base_fit']:6.2f} {tm.get('shape', 0.0):6.2f} {tm['screening']:6.2f} "
                  f"{tm['refits']:6.2f} {tm['validation']:6.2f} {tm['other']:6.2f} {total:6.2f} {cpu:6.2f} "
                  f"{load:>9} {oracle:6.2f}  {found}; {params} ({truth}){' [budget]' if res.budget_exhausted else ''}",
                  flush=True)
            if args.baseline:
                print(f"{'':12} {'':7} {run_baseline(args.baseline, body)}", flush=True)


if __name__ == "__main__":
    main()
