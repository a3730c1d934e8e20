"""Report figures read beside the correlations: the residual against time per output (as SITB's
`resid` shows both), and the profile-likelihood curves a fit computed (`options.profile`)."""
from __future__ import annotations

import numpy as np

from greyfit.schemas.fit import FitResult
from greyfit.schemas.text_report import level_percent
from greyfit.service.report.page import (
    MAX_OUTPUTS,
    MAX_PARAMETERS,
    MAX_RECORDS,
    Figure,
    Series,
    _grid_layout,
    _save,
    _short,
    _shown,
    _with_unit,
)


def residual_time_figure(plt, records: list[tuple[str, Series]], svg: bool = False,
                         notes: list[str] | None = None, units: dict[str, str] | None = None) -> Figure | None:
    """Measured minus simulated against time: one row per output, one column per record (`records`:
    (estimation or validation, its series)); the band is ±2 RMS of the residual shown. A trend, a
    step or a repeating shape there is what the model lacks; the correlations say only whether one
    is there."""
    notes = [] if notes is None else notes
    units = units or {}
    records = _shown(records, MAX_RECORDS, "records", "residuals against time", notes)
    outputs = _shown(sorted({o for _, r in records for o in r.measured}), MAX_OUTPUTS, "outputs",
                     "residuals against time", notes)
    if not records or not outputs:
        return None
    cols = len(records)
    fig, axes = plt.subplots(len(outputs), cols, figsize=(5.2 * cols, 2.2 * len(outputs) + 0.6),
                             squeeze=False, sharex="col")
    for c, (kind, rec) in enumerate(records):
        for r, out in enumerate(outputs):
            ax = axes[r][c]
            if out in rec.measured:
                e = rec.measured[out] - rec.simulated[out]
                ok = np.isfinite(e)
                rms = float(np.sqrt(np.mean(e[ok] ** 2))) if ok.any() else 0.0
                ax.axhspan(-2 * rms, 2 * rms, color="C2", alpha=0.12, label=f"±2 RMS ({rms:.3g})")
                ax.axhline(0, color="0.6", lw=0.8)
                ax.plot(rec.time, e, color="C0", lw=0.8)
                ax.legend(loc="upper right", fontsize=7, frameon=False)
            ax.set_ylabel(_with_unit(f"e({_short(out, 20)})", units, out))
            if r == 0:
                ax.set_title(f"{kind}: {_short(rec.name)}", fontsize=9)
            if r == len(outputs) - 1:
                ax.set_xlabel(_with_unit("t", units, "t"))
    _grid_layout(fig, len(outputs), cols, hgap=0.25)
    return _save(plt, fig, "residuals_time", "Residuals (measured minus simulated) against time, per output "
                 "and record; the band is ±2 RMS", svg)


def profile_figure(plt, fit: FitResult, svg: bool = False, notes: list[str] | None = None) -> Figure | None:
    """Each profiled parameter's re-optimised cost against its value, with the threshold whose
    crossings are the profile-likelihood interval (drawn as its two ends)."""
    profiles = [(name, p) for name, p in (fit.profile or {}).items() if p.values]
    if not profiles:
        return None
    profiles = _shown(profiles, MAX_PARAMETERS, "profiles", "profiles", [] if notes is None else notes)
    cols = min(3, len(profiles))
    rows = -(-len(profiles) // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 2.8 * rows + 0.4), squeeze=False)
    for ax in axes.flat[len(profiles):]:
        ax.set_visible(False)
    level = level_percent(fit.confidence_level)
    for ax, (name, p) in zip(axes.flat, profiles):
        costs = np.array([np.nan if c is None else c for c in p.costs], dtype=float)
        ax.plot(p.values, costs, color="C0", marker=".", ms=4, lw=1.0, label="profile cost")
        if p.threshold is not None:
            ax.axhline(p.threshold, color="C3", lw=0.8, ls="--", label=f"{level} threshold")
        for end in (p.lower, p.upper):
            if end is not None:
                ax.axvline(end, color="C2", lw=0.8)
        estimate = fit.parameters.get(name)
        if estimate is not None:
            ax.axvline(estimate.value, color="0.5", lw=0.8, ls=":")
        unit = fit.parameters[name].unit if estimate is not None else None
        ax.set_xlabel(f"{_short(name)} [{unit}]" if unit else _short(name))
        ax.set_ylabel("cost")
        ends = "unbounded" if p.lower is None or p.upper is None else f"[{p.lower:.4g}, {p.upper:.4g}]"
        ax.set_title(f"{_short(name, 20)}: {ends}" + (f" ({_short(p.note, 30)})" if p.note else ""), fontsize=8)
        ax.legend(fontsize=7, frameon=False)
    fig.tight_layout()
    return _save(plt, fig, "profiles", f"Profile likelihood: the cost with the other parameters re-optimised at "
                 f"each value; the {level} interval (green) is where it stays below the threshold (red)", svg)
