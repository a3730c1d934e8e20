"""The tables of the HTML report: verdict, estimates with units, metrics per output, warnings,
the model's equations, and version and date. Numbers are the result's own (as in the text report)."""
from __future__ import annotations

import html
from datetime import datetime, timezone
from typing import Any, Optional

from greyfit.schemas.discovery import DiscoveryResult
from greyfit.schemas.fit import FitResult
from greyfit.schemas.frequency import TransferFunctionModel
from greyfit.schemas.model import Model
from greyfit.schemas.text_report import converged, effective_quality, level_percent, timings_text


def _e(text) -> str:
    return html.escape(str(text))


def _n(value: Optional[float], fmt: str = ".6g") -> str:
    return "–" if value is None else format(value, fmt)


def _table(cls: str, head: list[str], rows: list[list[str]]) -> str:
    """Cells are already escaped."""
    th = "".join(f"<th>{h}</th>" for h in head)
    body = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in rows)
    return f'<table class="{cls}"><thead><tr>{th}</tr></thead><tbody>{body}</tbody></table>'


def verdict_html(fit: FitResult) -> str:
    """The header line: keyed on the solver's status and on `quality`, never on `success` alone
    (a converged but suspect fit is "converged, but suspect", not "not converged")."""
    quality = effective_quality(fit)
    state = "converged" if converged(fit) else "not converged"
    codes = ", ".join(dict.fromkeys(w.code for w in fit.warnings))
    reasons = f" ({_e(codes)}: see Warnings)" if quality != "good" and codes else ""
    flag = str(converged(fit)).lower()
    return (f'<p class="verdict quality-{quality}" data-quality="{quality}" data-converged="{flag}">'
            f"<b>{state}</b>, quality <b>{quality}</b>{reasons}<br>"
            f"{_e(fit.message)} ({_e(fit.solver.method.value)}, {fit.solver.return_status}, "
            f"{fit.solver.iterations} iterations){_choice_html(fit)}{_timings_html(fit)}</p>")


def _timings_html(fit: FitResult) -> str:
    timings = fit.solver.timings
    return f"<br>time: {_e(timings_text(timings))}" if timings else ""


def _choice_html(fit: FitResult) -> str:
    choice = fit.solver.method_choice
    return "" if choice is None else f"<br>{_e(choice.ran.value)} chosen by method auto: {_e(choice.reason)}"


def estimates_table(fit: FitResult) -> str:
    rows = []
    for name, p in fit.parameters.items():
        rel = f"{100 * p.stderr / abs(p.value):.2f} %" if p.stderr is not None and p.value != 0 else ""
        ci = f"[{p.ci95[0]:.6g}, {p.ci95[1]:.6g}]" if p.ci95 is not None else ""
        note = "fixed" if p.fixed else (f"at {p.at_bound} bound" if p.at_bound else "")
        rows.append([_e(name), f"{p.value:.6g}", "" if p.fixed else _n(p.stderr, ".3g"), rel, ci, _e(p.unit or ""),
                     f"{p.initial:.6g}", note])
    table = _table("estimates", ["parameter", "value", "stderr (1σ)", "rel.",
                                 f"{level_percent(fit.confidence_level)} CI", "unit", "initial", ""], rows)
    note = f"<p class='note'>covariance: {_e(fit.covariance_note)}</p>" if fit.covariance_note else ""
    return "<h2>Estimates</h2>" + table + note


def metrics_table(fit: FitResult) -> str:
    white = {a.output: a.whiteness.passed for a in fit.residual_analysis if a.whiteness.lags}
    rows = []
    for out, rmse in fit.metrics.rmse.items():
        f = fit.metrics.fit_percent.get(out)
        rows.append([_e(out), "estimation", _n(f, ".2f"), _n(None if f is None else 1 - f / 100, ".4f"),
                     _n(rmse, ".4g"), "" if out not in white else ("white" if white[out] else "not white")])
    if fit.validation is not None:
        v = fit.validation
        rows += [[_e(o), "validation", _n(v.fit_percent.get(o), ".2f"), _n(v.nrmse.get(o), ".4f"), _n(r, ".4g"), ""]
                 for o, r in v.rmse.items()]
    m = fit.metrics
    info = (f"<p>{m.ndata} data points, {m.nvarys} estimated (parameters and initial states); cost {_n(m.cost)}, "
            f"AIC {_n(m.aic, '.2f')}, BIC {_n(m.bic, '.2f')}</p>")
    return ("<h2>Metrics per output</h2>" + _table("metrics", ["output", "records", "fit %", "NRMSE", "RMSE",
                                                              "residual"], rows) + info)


def warnings_list(fit: FitResult) -> str:
    if not fit.warnings:
        return "<h2>Warnings</h2><p class='warnings-none'>none</p>"
    items = "".join(f"<li><code>{_e(w.code)}</code>: {_e(w.message)}</li>" for w in fit.warnings)
    return f"<h2>Warnings</h2><ul class='warnings'>{items}</ul>"


def loops_table(fit: FitResult) -> str:
    fr = fit.frequency_response
    if fr is None:
        return ""
    rows = [[_e(lp.setting), "yes" if lp.stable else "<b>NO</b>", _n(lp.max_real_part, ".4g")] for lp in fr.loops]
    return (f"<h2>Closed loops</h2><p>cost {_e(fr.cost_kind)}, stability {_e(fr.stability_handling)}</p>"
            + _table("loops", ["loop", "stable", "max Re(pole)"], rows))


def equations_html(model) -> str:
    """The model as it was fitted: equations, outputs, definitions, constraints (or num/den)."""
    if model is None:
        return ""
    lines: list[str] = []
    if isinstance(model, TransferFunctionModel):
        lines += [f"numerator (descending powers of s): {', '.join(model.numerator)}",
                  f"denominator: {', '.join(model.denominator)}"]
        if model.feedback is not None:
            lines.append(f"in feedback with C(s) = [{', '.join(model.feedback.controller.num)}] / "
                         f"[{', '.join(model.feedback.controller.den)}], measured {model.feedback.measured}")
    elif isinstance(model, Model):
        lhs = "{}[k+1]" if model.discrete is not None else "d{}/dt"
        lines += [f"{lhs.format(s)} = {e}" for s, e in model.equations.items()]
        lines += [f"{y} = {e}" for y, e in (model.outputs or {}).items()]
        lines += [f"{k} := {e}" for k, e in model.definitions.items()]
        lines += [f"subject to {c}" for c in model.constraints]
        if model.constants:
            lines.append("constants: " + ", ".join(f"{k} = {v:g}" for k, v in model.constants.items()))
        if model.units:
            lines.append("units: " + ", ".join(f"{k} [{u}]" for k, u in model.units.items()))
    return f"<h2>Model: {_e(model.name)}</h2><pre class='equations'>" + "\n".join(_e(x) for x in lines) + "</pre>"


def _before_after(result: DiscoveryResult) -> str:
    pairs: list[tuple[str, Any, Any]] = [("estimation", result.before, result.after)]
    if result.before.validation is not None and result.after.validation is not None:
        pairs.append(("validation", result.before.validation, result.after.validation))
    rows = [[_e(o), label, _n(b.rmse.get(o), ".4g"), _n(a.rmse.get(o), ".4g"), _n(b.fit_percent.get(o), ".2f"),
             _n(a.fit_percent.get(o), ".2f")] for o in result.before.rmse for label, b, a in pairs]
    rows.append(["BIC", "", _n(result.before.bic, ".1f"), _n(result.after.bic, ".1f"), "", ""])
    return _table("before-after", ["output", "records", "RMSE before", "RMSE after", "fit % before", "fit % after"],
                  rows)


def discovery_html(result: DiscoveryResult) -> str:
    def where(eq: str) -> str:
        return eq if eq.startswith("output") else f"d{eq}/dt"
    steps = "".join(f"<li>+ {_e(s.effect)} in {_e(where(s.equation))}: <code>{_e(s.term)}</code> "
                    f"(BIC −{s.evidence.bic_drop:.0f})</li>" for s in result.steps) or "<li>nothing added</li>"
    rejected = "".join(f"<li>{_e(r.effect)} (<code>{_e(r.term)}</code>): <b>{_e(r.reason)}</b>: {_e(r.detail)}</li>"
                       for r in result.rejected)
    return (f"<h2>Discovery</h2><p>{_e(result.conclusion)}</p><ul class='steps'>{steps}</ul>"
            + (f"<p>not kept:</p><ul>{rejected}</ul>" if rejected else "") + _before_after(result)
            + _next_experiment(result))


def _next_experiment(result: DiscoveryResult) -> str:
    """For each ambiguous step, the design request that would settle it: the experiment is the user's
    to run, so the page gives the body to send (POST /v1/designs, or `greyfit design --report`, whose
    page draws the designed input and its predicted gain)."""
    import json
    items = []
    for s in result.steps:
        if s.design is None:
            continue
        rivals = ", ".join(r.get("name", "?") for r in s.design.get("rivals", []) if isinstance(r, dict))
        items.append(f"<li>{_e(s.effect)} in {_e(s.equation)} against {_e(rivals or 'its runners-up')}: "
                     f"<details><summary>the design request</summary><pre class='design-request'>"
                     f"{_e(json.dumps(s.design, indent=1)[:20000])}</pre></details></li>")
    if not items:
        return ""
    return ("<h2>The next experiment</h2><p>These records cannot tell the rivals apart. Send a body below to "
            "<code>POST /v1/designs</code> (or save it and run <code>greyfit design BODY.json --report DIR</code>) "
            "for the input that separates them, with its predicted divergence; its report draws the input.</p>"
            f"<ul class='next-experiment'>{''.join(items)}</ul>")


def summary_html(fit: FitResult, discovery: Optional[DiscoveryResult], model) -> str:
    """Every table of the page, in reading order."""
    from greyfit import __version__
    when = datetime.now(timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    meta = f"<p class='meta'>greyfit {_e(__version__)} · report made {when}</p>"
    parts = [meta, verdict_html(fit)]
    if discovery is not None:
        parts.append(discovery_html(discovery))
    parts += [estimates_table(fit), metrics_table(fit), loops_table(fit), warnings_list(fit), equations_html(model)]
    return "\n".join(p for p in parts if p)
