"""Every spelling of a model discovers alike: random respellings of generated models, screened and discovered.

Models come from tests/generated_models.py (mechanical, electrical, thermal, fluid, chemical and
biological blocks of 2–5 states, each lacking one effect; 1 % white noise, two outputs; `--samples`
samples, 200 by default; a validation record in part 2).
The respellings come from tests/respell.py (difference sides swapped with the sign, sums and products
reordered, products distributed and factored, quotients split, 1/p for a division, negations moved,
sub-expressions moved into definitions).

Part 1 (`screen`): each model is fitted once; the declared spelling and `--per-model` respellings are
screened at that fit (candidate generation and the score test only, so it is cheap; the first
respelling in full, the others with the declared spelling's output sensitivities, which are the
same numbers and most of a screen's cost). A respelling is
*identical* when its candidate set (effect, equations, outputs, term, where scored) and its
significant candidates in the screen's ranking equal the declared spelling's; a *traceback* is any exception.

Part 2 (`discover`): the full discovery (`max_terms` 1) on the declared spelling and on one respelling
of `--discover` models; the *same answer* is the same steps (effect, equation, term, verdict) and the
declared parameters within 1 % of each other.

    OPENBLAS_NUM_THREADS=1 nice -n 10 python bench/bench_discovery_respell.py [--models 100] [--per-model 10]
        [--discover 20] [--part screen|discover|both]

Rates are printed with Wilson 95 % intervals, overall and per kind.
"""
from __future__ import annotations

import argparse
import sys
import time
import traceback
from collections import defaultdict
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from greyfit.schemas.discovery import DiscoverRequest  # noqa: E402
from greyfit.solvers.discovery import discover  # noqa: E402
from greyfit.solvers.fit import fit_model  # noqa: E402
from tests import generated_models as gm  # noqa: E402
from tests import respell as rs  # noqa: E402


def wilson(k: int, n: int, z: float = 1.96) -> str:
    """k/n with its Wilson 95 % interval, as text."""
    if n == 0:
        return "n/a"
    p = k / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return f"{k}/{n} = {100 * p:.1f} % [{100 * max(centre - half, 0):.1f}, {100 * min(centre + half, 1):.1f}]"


def screen_model(kind: str, seed: int, per_model: int, n: int) -> list[dict]:
    """The declared spelling and `per_model` respellings of one generated model, screened at one fit.

    The declared spelling and the first respelling are screened in full; the others reuse the declared
    spelling's output sensitivities (the same numbers: the cost of a screen), their candidates and
    equation scores from their own compiled model."""
    case = gm.generate(kind, seed)
    exp = gm.record(case, seed, n=n)
    fit = fit_model(rs.request_of(case.model, exp))
    full = rs.screen_of(case.model, exp, fit)
    reference = rs.candidate_set(case.model, exp, fit, output_scorer=full.output_scorer)
    rng = np.random.default_rng(seed)
    out = []
    for k in range(per_model):
        spelt = rs.respell(case.model, rng)
        try:
            got = rs.candidate_set(spelt, exp, fit, output_scorer=None if k == 0 else full.output_scorer)
            out.append({"kind": kind, "same": got == reference, "error": None})
        except Exception:   # the bench counts any traceback
            out.append({"kind": kind, "same": False, "error": traceback.format_exc(limit=3)})
    return out


def part_screen(models: int, per_model: int, n: int, start: int = 0) -> None:
    runs: list[dict] = []
    t0 = time.process_time()
    for i in range(start, start + models):
        kind = gm.KINDS[i % len(gm.KINDS)]
        try:
            mine = screen_model(kind, 1000 + i, per_model, n)
        except Exception:
            mine = [{"kind": kind, "same": False, "error": traceback.format_exc(limit=3)}] * per_model
        runs += mine
        print(f"model {i} {kind}: {sum(r['same'] for r in mine)}/{len(mine)} identical, "
              f"{sum(r['error'] is not None for r in mine)} tracebacks", flush=True)
    print(f"\nscreen: {len(runs)} respellings of {models} models ({time.process_time() - t0:.0f} CPU s)")
    print(f"{'kind':<12} {'identical candidates':<34} tracebacks")
    for kind in [*gm.KINDS, "all"]:
        mine = [r for r in runs if kind in ("all", r["kind"])]
        print(f"{kind:<12} {wilson(sum(r['same'] for r in mine), len(mine)):<34} "
              f"{sum(r['error'] is not None for r in mine)}")
    for r in runs:
        if r["error"]:
            print(r["error"])
            break


def answer(body: dict) -> tuple[list, dict]:
    res = discover(DiscoverRequest.model_validate(body))
    steps = [(s.effect, s.equation, s.term, s.verdict) for s in res.steps]
    return steps, {k: (v.value, v.stderr) for k, v in res.fit.parameters.items()}


def gap(params: dict, params2: dict) -> tuple[float, float]:
    """(largest relative difference, largest difference in standard errors) of the declared parameters."""
    rel = max(abs(a - params2[k][0]) / max(abs(a), 1e-12) for k, (a, _) in params.items())
    se = max(abs(a - params2[k][0]) / s if s and np.isfinite(s) and s > 0 else
             (0.0 if a == params2[k][0] else np.inf) for k, (a, s) in params.items())
    return rel, se


def part_discover(count: int, start: int = 0, n: int = 300) -> None:
    by_kind: dict[str, list[bool]] = defaultdict(list)
    errors = 0
    t0 = time.process_time()
    for i in range(start, start + count):
        kind = gm.KINDS[i % len(gm.KINDS)]
        case = gm.generate(kind, 2000 + i)
        exp, val = gm.record(case, 2000 + i, n=n), gm.record(case, 3000 + i, n=n, name="val")
        spelt = rs.respell(case.model, np.random.default_rng(i))
        body = {"experiments": [exp], "validation": [val], "method": "multiple_shooting",
                "discovery": {"max_terms": 1, "time_budget_s": 60}}
        try:
            steps, params = answer({**body, "model": case.model})
            steps2, params2 = answer({**body, "model": spelt})
        except Exception:
            errors += 1
            by_kind[kind].append(False)
            print(traceback.format_exc(limit=3))
            continue
        rel, se = gap(params, params2) if set(params) == set(params2) else (np.inf, np.inf)
        close = rel <= 0.01 or se <= 0.1
        by_kind[kind].append(steps == steps2 and close)
        print(f"{kind:<11} {steps} | respelt {'same' if steps == steps2 else steps2} "
              f"params: largest gap {100 * rel:.2g} % = {se:.2g} stderr", flush=True)
    flat = [x for v in by_kind.values() for x in v]
    print(f"\ndiscover: {count} models, declared vs respelt ({time.process_time() - t0:.0f} CPU s): "
          f"same answer {wilson(sum(flat), len(flat))}, tracebacks {errors}")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--models", type=int, default=100)
    ap.add_argument("--per-model", type=int, default=10)
    ap.add_argument("--discover", type=int, default=20)
    ap.add_argument("--start", type=int, default=0, help="first model (to split a run over processes)")
    ap.add_argument("--samples", type=int, default=200, help="samples of a record")
    ap.add_argument("--part", choices=("screen", "discover", "both"), default="both")
    args = ap.parse_args()
    if args.part in ("screen", "both"):
        part_screen(args.models, args.per_model, args.samples, args.start)
    if args.part in ("discover", "both"):
        part_discover(args.discover, args.start, args.samples)


if __name__ == "__main__":
    main()
