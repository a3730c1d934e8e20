"""Discovery figures of the report: metrics before/after, the overlay of the model with and
without the added terms (on the first estimation record and, where the request has them, the first
validation record: records the fit never saw), and the discrepancy dᵢ against the variable it
depends on most."""
from __future__ import annotations

import numpy as np

from greyfit.schemas.discovery import DiscoveryResult
from greyfit.service.report.page import (
    MAX_OUTPUTS,
    MEASURED_LINE,
    SIMULATED_LW,
    Figure,
    _save,
    _short,
    _shown,
    _simulated_series,
    _with_unit,
)

MAX_DISCREPANCIES = 4   # equations drawn (the most likely first)


def discovery_figures(plt, result: DiscoveryResult, request, svg: bool = False) -> tuple[list[Figure], list[str]]:
    figs: list[Figure] = []
    notes: list[str] = []
    units = dict(result.model.units)
    outs = _shown(list(result.before.rmse), 4 * MAX_OUTPUTS, "outputs", "discovery metrics", notes)
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.2))
    x = np.arange(len(outs))
    for ax, key, label in ((axes[0], "rmse", "RMSE"), (axes[1], "fit_percent", "fit %")):
        before = [getattr(result.before, key)[o] for o in outs]
        after = [getattr(result.after, key)[o] for o in outs]
        ax.bar(x - 0.2, before, 0.4, label="declared model", color="0.6")
        ax.bar(x + 0.2, after, 0.4, label="with the added terms", color="C0")
        ax.set_xticks(x, [_short(o, 20) for o in outs])
        ax.set_title(label, fontsize=9)
    axes[0].legend(fontsize=7, frameon=False)
    terms = "; ".join(f"+ {s.term} in d{s.equation}/dt" for s in result.steps) or "nothing added"
    fig.suptitle(_short(terms, 160), fontsize=8)
    fig.tight_layout()
    figs.append(_save(plt, fig, "discovery_metrics", "Before and after discovery", svg))
    shape = discrepancy_figure(plt, result, svg, notes)
    if shape is not None:
        figs.append(shape)
    if request is None or not result.steps:
        if request is None:
            notes.append("the before/after overlay needs the request (measured data)")
        return figs, notes
    from greyfit.solvers.data.preprocess import prepare_request
    prepared, _ = prepare_request(request)
    params = {k: v.value for k, v in result.fit.parameters.items()}
    added = {p.name for s in result.steps for p in s.parameters}
    without = {k: (0.0 if k.split("[", 1)[0] in added else v) for k, v in params.items()}
    kinds = [("estimation", prepared.experiments, result.fit.initial_states)]
    if prepared.validation:   # initial states estimated on each record's leading window, as validation does
        kinds.append(("validation", prepared.validation, {}))
    for kind, records, x0 in kinds:
        experiments = [exp.model_copy(update={"inputs": {**exp.inputs, **result.added_inputs.get(exp.name, {})}})
                       for exp in records[:1]]
        with_terms = _simulated_series(result.model, params, experiments, prepared.options, x0)[0]
        without_terms = _simulated_series(result.model, without, experiments, prepared.options, x0)[0]
        figs.append(_overlay(plt, kind, with_terms, without_terms, terms, units, svg, notes))
    return figs, notes


def _overlay(plt, kind: str, after, before, terms: str, units: dict, svg: bool, notes: list[str]) -> Figure:
    """One record's measured outputs under the final model with and without the added terms."""
    outputs = _shown(list(after.measured), MAX_OUTPUTS, "outputs", f"discovery overlay ({kind})", notes)
    fig, axes = plt.subplots(len(outputs), 1, figsize=(9, 2.4 * len(outputs) + 0.6), squeeze=False, sharex=True)
    for r, out in enumerate(outputs):
        ax = axes[r][0]
        # as in the compare figure: the measured line wide and light under the two models
        ax.plot(after.time, after.measured[out], label="measured", **MEASURED_LINE)
        ax.plot(before.time, before.simulated[out], color="C1", lw=SIMULATED_LW, zorder=2,
                label="without the added terms")
        ax.plot(after.time, after.simulated[out], color="C0", lw=SIMULATED_LW, zorder=3,
                label="with " + _short(terms, 100))
        ax.set_ylabel(_with_unit(_short(out), units, out))
        ax.legend(fontsize=7, frameon=False, loc="upper right")
    axes[-1][0].set_xlabel(_with_unit("t", units, "t"))
    fig.tight_layout()
    name = "discovery_overlay" if kind == "estimation" else "discovery_validation_overlay"
    return _save(plt, fig, name, f"{after.name} ({kind}): the final model with and without the added terms", svg)


def _pooled(series: dict) -> np.ndarray:
    """Per-experiment lists (dict name → values) as one array; nulls as NaN."""
    parts = [np.array([np.nan if v is None else v for v in values], dtype=float) for values in series.values()]
    return np.concatenate(parts) if parts else np.array([])


def discrepancy_figure(plt, result: DiscoveryResult, svg: bool, notes: list[str]) -> Figure | None:
    """dᵢ against the variable it depends on most, with the smooth law fitted to it, per equation.

    Drawn from `result.discrepancy` where the discovery returns one; a result without the field
    (older versions) or without a variable for an equation draws nothing for it."""
    discrepancy = getattr(result, "discrepancy", None)   # the field is newer than some results
    equations = [e for e in (getattr(discrepancy, "equations", None) or [])
                 if getattr(e, "variable", None) and getattr(e, "variable_samples", None)]
    if not equations:
        return None
    equations = _shown(equations, MAX_DISCREPANCIES, "equations", "discrepancy", notes)
    units = dict(getattr(getattr(result, "model", None), "units", None) or {})
    fig, axes = plt.subplots(1, len(equations), figsize=(4.4 * len(equations), 3.6), squeeze=False)
    for ax, eq in zip(axes[0], equations):
        x, d = _pooled(eq.variable_samples), _pooled(eq.samples)
        n = min(x.size, d.size)
        x, d = x[:n], d[:n]
        grid = np.asarray(getattr(eq, "law_grid", None) or [], dtype=float)
        law = np.asarray(getattr(eq, "law_values", None) or [], dtype=float)
        fitted = _pooled(getattr(eq, "law_samples", None) or {})
        label = "d (estimated)"
        if grid.size and grid.size == law.size and fitted.size == n:
            # partial residuals (as in a GAM's term plot): d less the fit's linear terms in the other
            # variables, which the curve holds at their means; the points then scatter about the curve by
            # the fit's residual alone, where raw d against one variable strays by those other terms
            d = d - fitted + np.interp(x, grid, law)
            label = "d, the other variables' linear terms removed"
        ax.plot(x, d, ".", ms=2.5, color="0.45", label=label)
        if grid.size and grid.size == law.size:
            ax.plot(grid, law, "-", color="C3", lw=1.4, label="fitted smooth law")
        elif getattr(eq, "law_samples", None):
            # an older result: its fitted values hold terms in the other states too, and drawn as a
            # line against the variable they zigzag
            notes.append(f"discrepancy of {eq.equation}: the result has no law on a grid of its variable "
                         "(written by an older version); the smooth law is not drawn")
        share = getattr(eq, "share_explained", None)
        where = eq.equation if str(eq.equation).startswith("output") else f"d{eq.equation}/dt"
        ax.set_title(f"{_short(where, 30)}: d against {_short(eq.variable, 30)}"
                     + (f" ({100 * share:.0f} % explained)" if share is not None else ""), fontsize=9)
        ax.set_xlabel(_with_unit(_short(eq.variable), units, eq.variable))   # a state's or input's unit
        ax.set_ylabel(f"d in {_short(where, 30)}")
        ax.legend(fontsize=7, frameon=False, loc="best")
    fig.tight_layout()
    return _save(plt, fig, "discrepancy", "The missing term as the data show it: the disturbance d estimated on "
                 "each equation, against the variable it depends on most, with the smooth function of that "
                 "variable fitted to it", svg)
