"""Figures and one self-contained HTML page for a fit or discovery result (matplotlib, Agg).

compare (measured vs simulated, estimation and validation), resid (residual autocorrelation and
input cross-correlation with the family-wise 99 % band; the residual against time and the profile
curves are in `report_residuals`), estimates with confidence intervals, the correlation matrix; for
a frequency fit Bode and Nyquist (`report_frequency`); for discovery the model before/after the
added terms and the discrepancy d against its variable. The tables (verdict, estimates, metrics,
warnings, equations) are in `report_html`.
"""
from __future__ import annotations

import base64
import html
import io
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from greyfit.schemas.design import DesignRequest, DesignResult
from greyfit.schemas.discovery import DiscoveryResult
from greyfit.schemas.fit import FitRequest, FitResult
from greyfit.schemas.frequency import FrequencyFitRequest
from greyfit.schemas.model import Model
from greyfit.schemas.report import ReportPublic, ReportRequest
from greyfit.schemas.text_report import level_percent
from greyfit.service.report.frequency import frequency_figures
from greyfit.service.report.html import summary_html


class ReportDependencyMissing(ImportError):
    """matplotlib is an optional extra."""


def _pyplot():
    try:
        import matplotlib
    except ImportError as exc:
        raise ReportDependencyMissing(
            "reports need matplotlib: pip install 'greyfit[report]' (bash scripts/install.sh report)") from exc
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


@dataclass
class Figure:
    name: str
    title: str
    png: bytes
    svg: str | None = None   # drawn only when asked for (files); the HTML page embeds the PNG


@dataclass
class Report:
    title: str
    figures: list[Figure] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    summary_html: str = ""


@dataclass
class Series:
    """Measured and simulated outputs of one record on its time grid."""

    name: str
    time: np.ndarray
    measured: dict[str, np.ndarray]
    simulated: dict[str, np.ndarray]


# A page stays readable, and a worker's CPU limit is not spent drawing, whatever the size of the
# result: past these, a figure shows the first ones and the page's notes say what was left out
MAX_RECORDS = 4       # columns of the compare figure
MAX_OUTPUTS = 6       # rows of the compare and residual figures
MAX_INPUTS = 3        # cross-correlation columns of the residual figure
MAX_PARAMETERS = 40   # rows of the estimates figure
MAX_LABELLED = 40     # correlation matrix: names on its axes up to this size

# measured outputs under simulated ones: the measured line wide and light, the simulated ones narrow
# and dark on top, so that at a 98 % fit both stay visible (the measured one as a halo where they agree)
MEASURED_LINE = {"color": "0.72", "lw": 3.2, "solid_capstyle": "round", "zorder": 1}
SIMULATED_LW = 1.0


def _short(name: str, limit: int = 40) -> str:
    """A name as a label: a 5 000-character one cost two seconds of text layout."""
    return name if len(name) <= limit else name[: limit - 1] + "…"


def _shown(items: list, limit: int, what: str, figure: str, notes: list[str]) -> list:
    if len(items) > limit:
        notes.append(f"{figure}: the first {limit} of {len(items)} {what} are drawn (the result has them all)")
    return items[:limit]


def _grid_layout(fig, rows: int, cols: int, left: float = 0.8, bottom: float = 0.5, top: float = 0.35,
                 wgap: float = 0.8, hgap: float = 0.6) -> None:
    """Margins and gaps in inches, for a grid of axes whose labels are short (an output's name, "t",
    "lag"). tight_layout measures every label by drawing each axes once more, which was half the
    time of a many-axes figure."""
    w, h = fig.get_size_inches()
    right = 0.2
    ax_w = max((w - left - right - (cols - 1) * wgap) / cols, 0.1)
    ax_h = max((h - bottom - top - (rows - 1) * hgap) / rows, 0.1)
    fig.subplots_adjust(left=left / w, right=1 - right / w, bottom=bottom / h, top=1 - top / h,
                        wspace=wgap / ax_w, hspace=hgap / ax_h)


def _save(plt, fig, name: str, title: str, svg: bool) -> Figure:
    # every figure is laid out before (tight_layout or _grid_layout): bbox_inches="tight" would draw it
    # once more
    png = io.BytesIO()
    fig.savefig(png, format="png", dpi=110)
    text = None
    if svg:
        out = io.StringIO()
        fig.savefig(out, format="svg")
        text = out.getvalue()
    plt.close(fig)
    return Figure(name, title, png.getvalue(), text)


def _simulated_series(model, params, experiments, options, initial_states, sources=None) -> list[Series]:
    from greyfit.solvers.model.compiler import compile_model
    from greyfit.solvers.simulation.simulate import simulate_arrays
    cm = compile_model(model)
    sims = simulate_arrays(model, params, experiments, options, initial_states, cm=cm,
                           provided_source=sources)
    return [Series(s.data.name, s.data.t,
                   {o: s.data.y[j] for j, o in enumerate(cm.outputs) if np.isfinite(s.data.y[j]).any()},
                   {o: s.outputs[j] for j, o in enumerate(cm.outputs)}) for s in sims]


def estimation_series(fit: FitResult, request: FitRequest | None, model) -> tuple[list[Series], list[Series]]:
    """(estimation, validation) records: simulated again from the request, else from the traces."""
    params = {k: v.value for k, v in fit.parameters.items()}
    if request is not None:
        from greyfit.solvers.data.preprocess import prepare_request
        prepared, _ = prepare_request(request)
        est = _simulated_series(model, params, prepared.experiments, prepared.options, fit.initial_states)
        val = []
        if prepared.validation and fit.validation is not None:
            x0 = {e.name: e.initial_state for e in fit.validation.experiments}
            val = _simulated_series(model, params, prepared.validation, prepared.options, x0)
        return est, val
    est = []
    for tr in fit.traces or []:
        sim = {k: np.array(v, dtype=float) for k, v in tr.simulated.items()}
        res = {k: np.array([np.nan if r is None else r for r in v], dtype=float) for k, v in tr.residuals.items()}
        est.append(Series(tr.name, np.array(tr.time), {k: sim[k] - res[k] for k in sim}, sim))
    return est, []


def _with_unit(label: str, units: dict[str, str], name: str) -> str:
    """`label [unit]` where `units` (a model's `units`) has one for `name`, else the label."""
    return f"{label} [{units[name]}]" if name in units else label


def compare_figure(plt, records: list[Series], kind: str, svg: bool = False,
                   notes: list[str] | None = None, units: dict[str, str] | None = None) -> Figure:
    notes = [] if notes is None else notes
    units = units or {}
    records = _shown(records, MAX_RECORDS, "records", f"compare ({kind})", notes)
    outputs = _shown(sorted({o for r in records for o in r.measured}), MAX_OUTPUTS, "outputs",
                     f"compare ({kind})", notes)
    cols = len(records)
    fig, axes = plt.subplots(len(outputs), cols, figsize=(5.2 * cols, 2.4 * len(outputs) + 0.6),
                             squeeze=False, sharex="col")
    for c, rec in enumerate(records):
        for r, out in enumerate(outputs):
            ax = axes[r][c]
            if out in rec.measured:
                y, yh = rec.measured[out], rec.simulated[out]
                ok = np.isfinite(y) & np.isfinite(yh)
                spread = max(float(np.linalg.norm(y[ok] - y[ok].mean())), 1e-300)
                fit = 100 * (1 - float(np.linalg.norm(yh[ok] - y[ok])) / spread)
                ax.plot(rec.time, y, label="measured", **MEASURED_LINE)
                ax.plot(rec.time, yh, color="C0", lw=SIMULATED_LW, label=f"simulated (fit {fit:.1f} %)", zorder=2)
                ax.legend(loc="upper right", fontsize=7, frameon=False)
            ax.set_ylabel(_with_unit(_short(out), units, out))
            if r == 0:
                ax.set_title(f"{kind}: {_short(rec.name)}", fontsize=9)
            if r == len(outputs) - 1:
                ax.set_xlabel(_with_unit("t", units, "t"))
    _grid_layout(fig, len(outputs), cols, hgap=0.25)
    return _save(plt, fig, f"compare_{kind}", f"Measured and simulated outputs ({kind} records)", svg)


def residual_figure(plt, fit: FitResult, svg: bool = False, notes: list[str] | None = None) -> Figure | None:
    notes = [] if notes is None else notes
    analyses = [a for a in fit.residual_analysis if a.whiteness.lags > 0]
    if not analyses:
        return None
    analyses = _shown(analyses, MAX_OUTPUTS, "outputs", "residuals", notes)
    inputs = _shown(sorted({u for a in analyses for u in a.cross_correlation}), MAX_INPUTS, "inputs",
                    "residuals", notes)
    fig, axes = plt.subplots(len(analyses), 1 + len(inputs), squeeze=False,
                             figsize=(4.2 * (1 + len(inputs)), 2.3 * len(analyses) + 0.5))
    for r, a in enumerate(analyses):
        ax = axes[r][0]
        lags = np.arange(len(a.autocorrelation))
        # vlines: one collection, where bar() draws a patch per lag (most of this figure's time)
        ax.vlines(lags[1:], 0, a.autocorrelation[1:], lw=2.5, color="C0" if a.whiteness.passed else "C3")
        ax.axhspan(-a.whiteness.bound, a.whiteness.bound, color="C2", alpha=0.15,
                   label=f"family-wise {100 * (1 - a.whiteness.level):.0f} % band (Šidák, {a.whiteness.lags} lags)")
        ax.legend(loc="upper right", fontsize=7, frameon=False)
        ax.set_title(f"autocorrelation of e({_short(a.output)}): {'white' if a.whiteness.passed else 'not white'}",
                     fontsize=9)
        ax.set_xlabel("lag [samples]")
        for c, u in enumerate(inputs, start=1):
            ax = axes[r][c]
            xc = np.array(a.cross_correlation.get(u, []))
            if xc.size:
                test = a.independence[u]
                k = np.arange(xc.size) - (xc.size - 1) // 2
                ax.vlines(k, 0, xc, lw=2.5, color="C0" if test.passed else "C3")
                ax.axhspan(-test.bound, test.bound, color="C2", alpha=0.15)
                ax.set_title(f"cross-correlation e({_short(a.output, 20)}) with {_short(u, 20)}", fontsize=9)
            ax.set_xlabel("lag [samples]")
    _grid_layout(fig, len(analyses), 1 + len(inputs), wgap=0.6, hgap=0.8)
    return _save(plt, fig, "residuals", "Residual whiteness and independence from the inputs. The bands are "
                 "family-wise (Šidák-corrected over the lags tested): a white, independent residual stays inside "
                 "at every lag at once with 99 % probability", svg)


def parameter_figure(plt, fit: FitResult, svg: bool = False, notes: list[str] | None = None) -> Figure | None:
    free = [(k, p) for k, p in fit.parameters.items() if not p.fixed]
    if not free:
        return None
    free = _shown(free, MAX_PARAMETERS, "free parameters", "estimates", [] if notes is None else notes)
    fig, ax = plt.subplots(figsize=(7, 0.45 * len(free) + 1.2))
    for i, (name, p) in enumerate(free):
        scale = abs(p.value) if p.value != 0 else 1.0
        if p.ci95 is not None:
            lo, hi = (p.ci95[0] - p.value) / scale * 100, (p.ci95[1] - p.value) / scale * 100
            # drawn as its two ends, not errorbar(): a result from elsewhere whose interval does not
            # hold its estimate (negative xerr) would fail the whole page
            ax.hlines(i, lo, hi, color="C0")
            ax.plot([lo, 0, hi], [i, i, i], color="C0", marker="o", markevery=[1], ls="none")
            ax.plot([lo, hi], [i, i], color="C0", marker="|", ms=9, ls="none")
        else:
            ax.plot([0], [i], "o", color="C3")
        unit = f" {p.unit}" if p.unit else ""
        label = f"{_short(name)} = {p.value:.5g}{unit}" + (
            f"  [{p.ci95[0]:.4g}, {p.ci95[1]:.4g}]" if p.ci95 is not None else " (no CI)")
        ax.annotate(label, (0, i), xytext=(8, 6), textcoords="offset points", fontsize=8)
    ax.set_yticks(range(len(free)), [_short(k) for k, _ in free])
    ax.axvline(0, color="0.7", lw=0.8)
    level = level_percent(fit.confidence_level)
    ax.set_xlabel(f"{level} confidence interval [% of the estimate]")
    ax.invert_yaxis()
    fig.tight_layout()
    return _save(plt, fig, "parameters", f"Estimates with their {level} confidence intervals (bars; the labels "
                 "give each interval in the parameter's unit; the standard errors are in the table)", svg)


def correlation_figure(plt, fit: FitResult, svg: bool = False, notes: list[str] | None = None) -> Figure | None:
    if fit.correlation is None or len(fit.correlation.names) < 2:
        return None
    names, m = fit.correlation.names, np.array(fit.correlation.matrix)
    n = len(names)
    # beyond MAX_LABELLED the matrix is drawn whole, unlabelled, at a fixed size
    size = (max(4.5, 1.0 + 0.55 * n), max(3.5, 0.8 + 0.5 * n)) if n <= MAX_LABELLED else (7.0, 6.0)
    fig, ax = plt.subplots(figsize=size)
    im = ax.imshow(m, cmap="RdBu_r", vmin=-1, vmax=1)
    if n <= MAX_LABELLED:
        ax.set_xticks(range(n), [_short(k) for k in names], rotation=60, ha="right", fontsize=8)
        ax.set_yticks(range(n), [_short(k) for k in names], fontsize=8)
    elif notes is not None:
        notes.append(f"correlation: {n} estimates, drawn without their names (in the order of the result's "
                     "correlation.names)")
    if n <= 12:
        for i in range(n):
            for j in range(n):
                ax.text(j, i, f"{m[i, j]:.2f}", ha="center", va="center", fontsize=7,
                        color="white" if abs(m[i, j]) > 0.6 else "black")
    fig.colorbar(im, ax=ax, fraction=0.046)
    fig.tight_layout()
    return _save(plt, fig, "correlation", "Correlation of the estimates", svg)


def _report_model(result, request):
    """The model to simulate: the one the result carries, else the request's (older results)."""
    fit = result.fit if isinstance(result, DiscoveryResult) else result
    model = result.model if isinstance(result, DiscoveryResult) else fit.model
    if model is None and request is not None and not isinstance(request, FrequencyFitRequest):
        model = request.model
    return model


def _time_domain_figures(plt, report: Report, fit: FitResult, request, model, svg: bool) -> None:
    if fit.frequency_response is not None:
        report.figures += frequency_figures(plt, fit.frequency_response, svg, report.notes)
        return
    time_request = request if isinstance(request, FitRequest) else None
    if time_request is not None and not isinstance(model, Model):
        time_request = None   # nothing to simulate the records with
    from greyfit.service.report.residuals import residual_time_figure
    est, val = estimation_series(fit, time_request, model)
    units = dict(model.units) if isinstance(model, Model) else {}
    if est:
        report.figures.append(compare_figure(plt, est, "estimation", svg, report.notes, units))
    else:
        report.notes.append("no measured-vs-simulated figure: give the request, or fit with return_traces")
    if val:
        report.figures.append(compare_figure(plt, val, "validation", svg, report.notes, units))
    records = [("estimation", r) for r in est] + [("validation", r) for r in val]
    figure = residual_time_figure(plt, records, svg, report.notes, units)
    if figure is not None:
        report.figures.append(figure)


def build_report(req: ReportRequest, svg: bool = False) -> Report:
    """Render every figure the result (and request) allow, as PNG and, if `svg`, SVG too; notes say
    what could not be drawn."""
    from greyfit.service.report.discovery import discovery_figures
    result, request = req.result, req.request
    if isinstance(result, DesignResult):
        from greyfit.service.report.design import design_report
        return design_report(result, request if isinstance(request, DesignRequest) else None, req.title, svg)
    plt = _pyplot()
    discovery = result if isinstance(result, DiscoveryResult) else None
    fit = result.fit if isinstance(result, DiscoveryResult) else result
    model = _report_model(result, request)
    report = Report(title=req.title or ("greyfit discovery report" if discovery else "greyfit fit report"))
    if discovery and isinstance(request, FitRequest) and discovery.added_inputs:   # series the augmented model needs
        added = discovery.added_inputs
        request = request.model_copy(update={"experiments": [
            e.model_copy(update={"inputs": {**e.inputs, **added.get(e.name, {})}})
            for e in request.experiments]})
    _time_domain_figures(plt, report, fit, request, model, svg)
    from greyfit.service.report.residuals import profile_figure
    for make in (residual_figure, parameter_figure, profile_figure, correlation_figure):
        figure = make(plt, fit, svg, report.notes)
        if figure is not None:
            report.figures.append(figure)
    if discovery:
        figs, notes = discovery_figures(plt, discovery, request if isinstance(request, FitRequest) else None, svg)
        report.figures += figs
        report.notes += notes
    report.summary_html = summary_html(fit, discovery, model)
    return report


def render_html(report: Report) -> str:
    """One page; figures as base64 PNG. A small script marks each decoded figure (data-rendered)."""
    figures = "\n".join(
        f'<figure id="fig-{f.name}" class="figure"><img alt="{html.escape(f.title)}" '
        f'src="data:image/png;base64,{base64.b64encode(f.png).decode()}">'
        f"<figcaption>{html.escape(f.title)}</figcaption></figure>" for f in report.figures)
    notes = "".join(f"<li>{html.escape(n)}</li>" for n in report.notes)
    return f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{html.escape(report.title)}</title>
<style>body{{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}}
table{{border-collapse:collapse;margin:0.5em 0}}td,th{{border:1px solid #ccc;padding:2px 8px;text-align:right}}
td:first-child,th:first-child{{text-align:left}}th{{background:#f4f4f4}}h2{{font-size:1.15em;margin-top:1.4em}}
.verdict{{padding:6px 10px;border-left:5px solid #999}}.quality-good{{border-color:#2a7}}
.quality-suspect{{border-color:#d90;background:#fff8e6}}.quality-failed{{border-color:#c33;background:#fdecec}}
.meta{{color:#666;font-size:90%}}pre.equations{{background:#f7f7f7;padding:8px;overflow-x:auto}}
figure{{margin:1.5em 0}}img{{max-width:100%}}figcaption{{color:#555;font-size:90%}}</style></head>
<body><h1>{html.escape(report.title)}</h1>
{report.summary_html}
{f"<ul class='notes'>{notes}</ul>" if notes else ""}
{figures}
<script>window.addEventListener("load", function () {{
  document.querySelectorAll("figure img").forEach(function (img) {{
    img.setAttribute("data-rendered", img.naturalWidth + "x" + img.naturalHeight); }});
  document.body.setAttribute("data-figures", document.querySelectorAll("figure img").length);
}});</script>
</body></html>
"""


def report_public(req: ReportRequest) -> ReportPublic:
    report = build_report(req)
    return ReportPublic(html=render_html(report), figures=[f.name for f in report.figures], notes=report.notes)


def write_report(req: ReportRequest, out_dir: Path, formats: tuple[str, ...] = ("png", "svg")) -> list[Path]:
    """Write every figure (PNG and SVG) and report.html to out_dir; return the paths."""
    report = build_report(req, svg="svg" in formats)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for f in report.figures:
        if "png" in formats:
            paths.append(out_dir / f"{f.name}.png")
            paths[-1].write_bytes(f.png)
        if "svg" in formats and f.svg is not None:   # (drawn whenever svg is asked for)
            paths.append(out_dir / f"{f.name}.svg")
            paths[-1].write_text(f.svg)
    page = out_dir / "report.html"
    page.write_text(render_html(report))
    return paths + [page]
