"""The worked example of docs/discovery.md: a heated block that loses heat by radiation as well as
convection, declared with convection only, one thermocouple (tests/shape_systems.py).

Prints the shape the discovery finds (the disturbance on dT/dt against T, thinned, with the smooth
law fitted to it), how well candidate laws agree with that shape, and before/after on the
estimation and validation records for the loop as it is and with T⁴ − Ta⁴ given as a candidate.

    OPENBLAS_NUM_THREADS=1 python bench/thermal_worked_example.py [--points 12] [--figures DIR]

`--figures DIR` also writes the discovery's report (PNG figures and report.html, `pip install -e
.[report]`) to DIR: `discrepancy.png` is the shape figure of docs/discovery.md (docs/thermal_shape.png),
`discovery_overlay.png` the final model with and without the added term (docs/thermal_overlay.png).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from greyfit.schemas.discovery import DiscoverRequest  # noqa: E402
from greyfit.schemas.fit import FitRequest  # noqa: E402
from greyfit.solvers.discovery import discover  # noqa: E402
from greyfit.solvers.discovery.shape import estimate_shape  # noqa: E402
from greyfit.solvers.discovery.shape_relate import shape_agreement  # noqa: E402
from greyfit.solvers.fit import fit_model  # noqa: E402
from tests import shape_systems as ss  # noqa: E402

TA = ss.THERMAL["Ta"]


def body(candidates=()):
    return {"model": ss.thermal_model(), "method": "multiple_shooting",
            "options": {"input_interpolation": "zoh"},
            "experiments": [ss.thermal_record(1)], "validation": [ss.thermal_record(2, name="val")],
            "discovery": {"candidates": list(candidates)}}


def show_shape(points: int) -> None:
    b = body()
    req = FitRequest.model_validate({k: v for k, v in b.items() if k != "discovery"})
    fit = fit_model(req)
    shape = estimate_shape(req, fit)
    best = shape.estimates[0]
    print(f"most likely equation: {best.equation}; variable: {best.variable}; a smooth function of it explains "
          f"{100 * best.share_explained:.1f} % of d (next: {best.alternatives})")
    truth = 0.005 * np.std(b["experiments"][0]["outputs"]["T_meas"])
    print(f"noise level {shape.noise_level['T_meas']:.3f} K (truth {truth:.3f} K)")
    temp, d, law = best.variables["T"][0], best.d[0], best.law[0]
    order = np.argsort(temp)
    print("\n| T (K) | d (K/s) | smooth law (K/s) |\n|---|---|---|")
    for i in order[np.linspace(0, temp.size - 1, points).astype(int)]:
        print(f"| {temp[i]:.1f} | {d[i]:.5f} | {law[i]:.5f} |")
    print("\nagreement of laws with the shape (share of d explained, with terms linear in T and P):")
    for name, g in (("T^4 - Ta^4", temp ** 4 - TA ** 4), ("T^2", temp ** 2), ("T^3", temp ** 3),
                    ("T|T - Ta|", temp * np.abs(temp - TA)), ("exp(-1000/T)", np.exp(-1000 / temp))):
        print(f"  {name:14s} {shape_agreement(best, [g]):.4f}")


def show_loop(candidates, label: str, figures: Path | None = None) -> None:
    req = DiscoverRequest.model_validate(body(candidates))
    res = discover(req)
    if figures is not None:
        from greyfit.schemas.report import ReportRequest
        from greyfit.service.report.page import write_report
        title = "Heated block with radiative loss, declared with convection only"
        paths = write_report(ReportRequest(result=res, request=req, title=title), figures, ("png",))
        print("report written: " + ", ".join(str(p) for p in paths))
    p = res.fit.parameters
    print(f"\n{label}: {res.conclusion}")
    print(f"  C = {p['C'].value:.1f} (truth {ss.THERMAL['C']}), h = {p['h'].value:.4f} (truth {ss.THERMAL['h']})"
          + "".join(f", {s.parameters[0].name} = {s.parameters[0].value:.4g}" for s in res.steps if s.parameters))
    print(f"  RMSE estimation {res.before.rmse['T_meas']:.3f} -> {res.after.rmse['T_meas']:.3f} K; validation "
          f"{res.before.validation.rmse['T_meas']:.3f} -> {res.after.validation.rmse['T_meas']:.3f} K; "
          f"unexplained: {res.unexplained is not None}; {res.wall_time_s:.1f} s")


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--points", type=int, default=12)
    ap.add_argument("--figures", type=Path, default=None, help="write the discovery's report (PNG) here")
    args = ap.parse_args()
    show_shape(args.points)
    show_loop([], "the loop with its library", args.figures)
    # the loop adds a term inside the numerator of (…)/C, so s keeps its units (W/K⁴)
    rad = {"equation": "T", "term": "-(T^4 - Ta^4)", "parameter": "s", "value": 0.0}
    show_loop([rad], "with T^4 - Ta^4 as a candidate")
    print(f"  truth s = {ss.THERMAL['s']:.4g}")


if __name__ == "__main__":
    main()
