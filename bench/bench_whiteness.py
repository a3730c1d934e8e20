"""Monte Carlo calibration of the residual tests (solvers/checks/diagnostics.py): false alarms and power.

Compares, on the same residuals, the old rule (max |r(k)| over the lags against the per-lag 99 % band
2.58/√N, as MATLAB's resid draws it), the current Šidák-corrected max test (family-wise 1 %), and a
Ljung-Box portmanteau Q against χ²(25) at 1 % as a peer. Prints one table per part:

  synthetic  white Gaussian residuals, AR(1) 0.3 / 0.5, a residual with a missing input-driven part,
             and a coloured residual independent of a slowly varying input (independence test)
  fits       residuals of real fits (msd, Duffing) of a complete model with white measurement noise,
             and of an incomplete one (the Duffing's cubic spring left out): the verdicts and how
             often `auto` switched the HAC covariance on (old: what the old rule would have done), and how
             often the quality verdict was not `good`

    python bench/bench_whiteness.py [--runs 2000] [--seeds 50] [--part synthetic|fits|all]
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.stats import chi2

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from greyfit.solvers.checks.diagnostics import LEVEL, MAX_LAGS, residual_analysis, sidak_z  # noqa: E402

OLD_Z = 2.58


def ljung_box_rejects(acf: np.ndarray, n: int, level: float = 0.01) -> bool:
    k = np.arange(1, acf.size)
    q = n * (n + 2) * float(np.sum(acf[1:] ** 2 / (n - k)))
    return q > chi2.ppf(1 - level, acf.size - 1)


def verdicts(resid: np.ndarray, u: np.ndarray) -> dict[str, bool]:
    """Rejections (True = flagged) of each rule on one residual."""
    a = residual_analysis("y", [(np.zeros(resid.size), resid, {"u": u})])
    n = resid.size
    acf = np.asarray(a.autocorrelation)
    xc = np.asarray(a.cross_correlation["u"])
    return {"white old": bool(np.max(np.abs(acf[1:])) > OLD_Z / np.sqrt(n)),
            "white new": not a.whiteness.passed,
            "white LB": ljung_box_rejects(acf, n),
            "indep old": bool(np.max(np.abs(xc)) > OLD_Z / np.sqrt(n)),
            "indep new": not a.independence["u"].passed}


def ar1(rng, n: int, phi: float) -> np.ndarray:
    e = rng.standard_normal(n + 200)
    out = np.empty_like(e)
    out[0] = e[0]
    for i in range(1, e.size):
        out[i] = phi * out[i - 1] + e[i]
    return out[200:]


def smooth_input(rng, n: int) -> np.ndarray:
    """A multisine spanning ~10 samples to the record length (slowly varying, strongly coloured)."""
    t = np.arange(n)
    freqs = np.geomspace(1.0 / n, 0.1, 8)
    return sum(np.sin(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi)) for f in freqs)


def lowpass(x: np.ndarray, pole: float) -> np.ndarray:
    out = np.empty_like(x)
    acc = 0.0
    for i, v in enumerate(x):
        acc = pole * acc + (1 - pole) * v
        out[i] = acc
    return out


CASES = {
    "white residual, white input": lambda rng, n: (rng.standard_normal(n), rng.standard_normal(n)),
    "white residual, smooth input": lambda rng, n: (rng.standard_normal(n), smooth_input(rng, n)),
    "AR(1) 0.3": lambda rng, n: (ar1(rng, n, 0.3), rng.standard_normal(n)),
    "AR(1) 0.5": lambda rng, n: (ar1(rng, n, 0.5), rng.standard_normal(n)),
    "AR(1) 0.5, smooth input (indep. null)": lambda rng, n: (ar1(rng, n, 0.5), smooth_input(rng, n)),
    "white + missing input part (std 0.3)": None,   # built below: needs the same u twice
}


def missing_part(rng, n):
    u = rng.standard_normal(n)
    part = lowpass(np.concatenate([np.zeros(1), u[:-1]]), 0.8)     # u delayed one sample and filtered
    return rng.standard_normal(n) + 0.3 * part / part.std(), u


CASES["white + missing input part (std 0.3)"] = missing_part


def synthetic(runs: int) -> None:
    keys = ["white old", "white new", "white LB", "indep old", "indep new"]
    print(f"\n## synthetic residuals, {runs} runs per cell: % flagged (family-wise level of the new tests 1 %)")
    print("| case | N | " + " | ".join(keys) + " |")
    print("|---|---|" + "---|" * len(keys))
    for case, make in CASES.items():
        for n in (200, 1000, 5000):
            rng = np.random.default_rng(n)
            reps = runs if n < 5000 else max(runs // 2, 1)
            count = dict.fromkeys(keys, 0)
            for _ in range(reps):
                e, u = make(rng, n)
                for k, v in verdicts(e, u).items():
                    count[k] += v
            print(f"| {case} | {n} | " + " | ".join(f"{100 * count[k] / reps:.1f}" for k in keys) + " |",
                  flush=True)


def _fit_cases(seeds: int):
    from tests import partial_systems as ps
    from tests.systems import msd_experiment, msd_model, simulate_msd
    duffing_full = ps.duffing_model()
    duffing_full["parameters"] = duffing_full["parameters"] + [{"name": "k3", "value": 1.0}]
    duffing_full["equations"] = {"y": "yd", "yd": "(u - d*yd - k*y - k3*y^3)/m"}
    for n in (200, 1000):
        t = np.linspace(0, 40, n)
        x = simulate_msd(t)
        yield (f"msd complete, N={n}, x & v noise 0.02", "complete",
               [{"model": msd_model(), "experiments": [msd_experiment(t, x, noise=0.02, seed=s)]}
                for s in range(seeds)])
    for n in (201, 1501):
        yield (f"Duffing complete, N={n}, noise 1 %", "complete",
               [{"model": duffing_full, "experiments": [ps.duffing_record(s, n=n)]} for s in range(seeds)])
    for noise in (0.05, 0.2):
        yield (f"Duffing without k3, N=1501, noise {noise:.0%}", "incomplete",
               [{"model": ps.duffing_model(), "experiments": [ps.duffing_record(s, noise=noise)]}
                for s in range(seeds)])


def fits(seeds: int) -> None:
    from greyfit.schemas import FitRequest
    from greyfit.solvers.fit import fit_model
    keys = ["white old", "white new", "white LB", "indep old", "indep new", "HAC old", "HAC new", "suspect"]
    print(f"\n## residuals of real fits (default method), {seeds} seeds: % flagged per output test")
    print("| case | model | " + " | ".join(keys) + " |")
    print("|---|---|" + "---|" * len(keys))
    for case, kind, requests in _fit_cases(seeds):
        count = dict.fromkeys(keys, 0)
        tests = 0
        for req in requests:
            res = fit_model(FitRequest.model_validate(req))
            count["HAC new"] += any(w.code == "robust_covariance" for w in res.warnings)
            count["suspect"] += res.quality != "good"
            old_flags = []
            for a in res.residual_analysis:
                tests += 1
                acf = np.asarray(a.autocorrelation)
                n = round((sidak_z(LEVEL, a.whiteness.lags) / a.whiteness.bound) ** 2)
                xc = np.concatenate([np.asarray(v) for v in a.cross_correlation.values()])
                old_flags.append(bool(np.max(np.abs(acf[1:])) > OLD_Z / np.sqrt(n)))
                count["white old"] += old_flags[-1]
                count["white new"] += not a.whiteness.passed
                count["white LB"] += ljung_box_rejects(acf, n)
                count["indep old"] += bool(np.max(np.abs(xc)) > OLD_Z / np.sqrt(n))
                count["indep new"] += not all(t.passed for t in a.independence.values())
            count["HAC old"] += any(old_flags)     # the old `auto` rule: any output's old test failed
        per = {k: (tests if k.startswith(("white", "indep")) else len(requests)) for k in keys}
        print(f"| {case} | {kind} | " + " | ".join(f"{100 * count[k] / per[k]:.0f}" for k in keys) + " |",
              flush=True)


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, default=2000)
    ap.add_argument("--seeds", type=int, default=50)
    ap.add_argument("--part", choices=["synthetic", "fits", "all"], default="all")
    args = ap.parse_args()
    assert MAX_LAGS == 25
    if args.part in ("synthetic", "all"):
        synthetic(args.runs)
    if args.part in ("fits", "all"):
        fits(args.seeds)


if __name__ == "__main__":
    main()
