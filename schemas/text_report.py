"""Text reports for people: fit, discovery and simulation results as lmfit's `fit_report()` does.

Only formatting: every number printed is one the result holds (no numerics, no I/O), so the report
and the JSON always agree. `FitResult.report()`, `DiscoveryResult` and `SimulateResult` summaries and
`greyfit fit|discover|simulate --summary` all come from here.
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any, Optional

if TYPE_CHECKING:
    from greyfit.schemas.design import DesignResult
    from greyfit.schemas.discovery import DiscoveryResult
    from greyfit.schemas.fit import FitResult
    from greyfit.schemas.simulate import SimulateResult

# solver statuses that mean the optimiser (or the closed form, the simulation, the online
# estimator) finished as asked; `quality` may still doubt the answer
CONVERGED_STATUSES = frozenset({"Solve_Succeeded", "Solved_To_Acceptable_Level", "Linear_Least_Squares",
                                "Simulation", "Online_Estimate"})
INDENT = "    "


def converged(result: "FitResult") -> bool:
    """Whether the solver finished as asked (independent of `quality`)."""
    return result.solver.return_status in CONVERGED_STATUSES


def effective_quality(result: "FitResult") -> str:
    """`quality`, except that a result with `success: false` is never `good` (a frequency fit whose
    closed loop came out unstable, or that did not converge, carries no quality verdict of its own)."""
    return "failed" if result.quality == "good" and not result.success else result.quality


def verdict(result: "FitResult") -> str:
    """One line: converged or not, and the quality with its reasons (warning codes)."""
    codes = ", ".join(dict.fromkeys(w.code for w in result.warnings))
    quality = effective_quality(result)
    if not converged(result):
        return f"not converged ({result.solver.return_status}); quality {quality}"
    if quality == "good":
        return "converged; quality good"
    return f"converged, but quality {quality}" + (f": {codes}" if codes else f": {result.message}")


def level_percent(level: float) -> str:
    """A confidence level as people write it: 0.95 -> "95 %", 0.9 -> "90 %", 0.975 -> "97.5 %"."""
    return f"{100 * level:.4g} %"


def timings_text(timings: dict[str, float]) -> str:
    """A fit's wall time and its stages (`SolverInfo.timings`) on one line, the empty ones left out.

    Parameters
    ----------
    timings : dict of str to float
        Stage -> seconds.

    Returns
    -------
    str
        E.g. "48 ms: prepare 4.1, checks before 4.9, solve 28, diagnostics 3.0, checks after 8.0".
    """
    total = sum(timings.values())
    unit, scale = ("s", 1.0) if total >= 1 else ("ms", 1e3)
    parts = [f"{name.replace('_', ' ')} {scale * v:{'.2g' if scale * v < 10 else '.0f'}}"
             for name, v in timings.items() if scale * v >= 0.05]
    head = f"{scale * total:.3g} {unit}"
    return head + (": " + ", ".join(parts) if parts else "")


def _num(value: Optional[float], fmt: str = ".6g") -> str:
    return "-" if value is None else format(value, fmt)


def _table(rows: list[list[str]], right: frozenset[int] | set[int] = frozenset()) -> list[str]:
    """Rows of cells as aligned columns (the first row is the header)."""
    widths = [max(len(r[c]) for r in rows) for c in range(len(rows[0]))]
    out = []
    for r in rows:
        cells = [cell.rjust(w) if c in right else cell.ljust(w) for c, (cell, w) in enumerate(zip(r, widths))]
        out.append(INDENT + "  ".join(cells).rstrip())
    return out


def _header(result: "FitResult") -> list[str]:
    m, s = result.metrics, result.solver
    model = result.model
    lines = ["[[Fit]]"]
    if model is not None:
        lines.append(f"{INDENT}model:        {model.name}")
    choice = s.method_choice
    lines.append(f"{INDENT}method:       {s.method.value}" + (" (chosen by method auto)" if choice else ""))
    if choice is not None:
        lines.append(f"{INDENT}why:          {choice.reason}")
    lines += [f"{INDENT}status:       {result.status}: {result.message}",
              f"{INDENT}verdict:      {verdict(result)}",
              f"{INDENT}solver:       {s.return_status}, {s.iterations} iterations, {s.starts} start(s), "
              f"{s.wall_time_s:.2f} s",
              *([f"{INDENT}time:         {timings_text(s.timings)}"] if s.timings else []),
              f"{INDENT}data points:  {m.ndata}",
              f"{INDENT}variables:    {m.nvarys} (free parameters and estimated initial states)",
              f"{INDENT}cost:         {_num(m.cost, '.6g')}",
              f"{INDENT}AIC, BIC:     {_num(m.aic, '.2f')}, {_num(m.bic, '.2f')}"]
    return lines


def _parameter_rows(result: "FitResult") -> list[str]:
    level = level_percent(result.confidence_level)
    rows = [["name", "value", "stderr", "rel.", f"{level} CI", "unit", "initial", "note"]]
    for name, p in result.parameters.items():
        rel = (f"{100 * p.stderr / abs(p.value):.2f} %" if p.stderr is not None and p.value != 0 else "")
        ci = f"[{p.ci95[0]:.6g}, {p.ci95[1]:.6g}]" if p.ci95 is not None else ""
        note = "fixed" if p.fixed else (f"at {p.at_bound} bound" if p.at_bound else "")
        if not p.fixed and p.stderr is None:
            note = (note + "; " if note else "") + "no stderr"
        rows.append([name, f"{p.value:.6g}", _num(p.stderr, ".3g") if not p.fixed else "", rel, ci,
                     p.unit or "", f"{p.initial:.6g}", note])
    lines = [f"[[Parameters]]  (CI at the {level} confidence level, options.confidence_level; "
             "rel. = stderr / |value|)"]
    lines += _table(rows, right={1, 2, 3, 6})
    if result.covariance_note:
        lines.append(f"{INDENT}covariance: {result.covariance_note}")
    return lines


def _initial_state_rows(result: "FitResult") -> list[str]:
    states = {k: v for k, v in result.initial_states.items() if v}
    if not states:
        return []
    return ["[[Initial states]]"] + [f"{INDENT}{name}: " + ", ".join(f"{s} = {x:.6g}" for s, x in x0.items())
                                     for name, x0 in states.items()]


def _correlation_rows(result: "FitResult", min_correlation: float) -> list[str]:
    lines = [f"[[Correlations]]  (|r| > {min_correlation:g})"]
    corr = result.correlation
    if corr is None:
        return lines + [f"{INDENT}not available (no covariance)"]
    pairs = [(abs(corr.matrix[i][j]), corr.names[i], corr.names[j], corr.matrix[i][j])
             for i in range(len(corr.names)) for j in range(i + 1, len(corr.names))
             if abs(corr.matrix[i][j]) > min_correlation]
    if not pairs:
        return lines + [f"{INDENT}none"]
    return lines + _table([[f"C({a}, {b})", f"{r:+.4f}"] for _, a, b, r in sorted(pairs, reverse=True)],
                          right={1})


def _output_rows(result: "FitResult") -> list[str]:
    rows = [["data set" if result.frequency_response is not None else "output", "records", "fit %", "NRMSE", "RMSE",
             "residual"]]
    white = {a.output: a.whiteness.passed for a in result.residual_analysis if a.whiteness.lags}
    for out, rmse in result.metrics.rmse.items():
        fit = result.metrics.fit_percent.get(out)
        nrmse = None if fit is None else 1 - fit / 100
        resid = "" if out not in white else ("white" if white[out] else "not white")
        rows.append([out, "estimation", _num(fit, ".2f"), _num(nrmse, ".4f"), _num(rmse, ".4g"), resid])
    val = result.validation
    if val is not None:
        for out, rmse in val.rmse.items():
            rows.append([out, "validation", _num(val.fit_percent.get(out), ".2f"), _num(val.nrmse.get(out), ".4f"),
                         _num(rmse, ".4g"), ""])
    return ["[[Outputs]]  (fit % = 100 (1 - NRMSE), NRMSE = |y - ŷ| / |y - mean(y)|)"] + _table(rows, {2, 3, 4})


def _frequency_rows(result: "FitResult") -> list[str]:
    fr = result.frequency_response
    if fr is None:
        return []
    lines = [f"[[Frequency response]]  cost {fr.cost_kind}, stability {fr.stability_handling}: "
             f"{'every closed loop stable' if fr.stable else 'UNSTABLE closed loop'}"]
    rows = [["loop", "stable", "max Re(pole)"]]
    rows += [[lp.setting, "yes" if lp.stable else "NO", _num(lp.max_real_part, ".4g")] for lp in fr.loops]
    return lines + _table(rows, {2})


def _warning_rows(result: "FitResult") -> list[str]:
    lines = ["[[Warnings]]"]
    if not result.warnings:
        return lines + [f"{INDENT}none"]
    return lines + [f"{INDENT}{w.code}: {w.message}" for w in result.warnings]


def fit_report(result: "FitResult", *, min_correlation: float = 0.9) -> str:
    """The text report of a fit: header, parameters, correlations, outputs, warnings.

    Parameters
    ----------
    result : FitResult
        Any fit result (time-domain, frequency, online).
    min_correlation : float
        Pairs of estimates whose |correlation| exceeds this are listed.
    """
    sections = [_header(result), _parameter_rows(result), _initial_state_rows(result),
                _correlation_rows(result, min_correlation),
                _output_rows(result), _frequency_rows(result), _warning_rows(result)]
    return "\n".join(line for section in sections for line in section)


def _discovery_table(result: "DiscoveryResult") -> list[str]:
    rows_of: list[tuple[str, Any, Any]] = [("estimation", result.before, result.after)]   # both have rmse, fit %
    if result.before.validation is not None and result.after.validation is not None:
        rows_of.append(("validation", result.before.validation, result.after.validation))
    rows = [["output", "records", "RMSE before", "RMSE after", "fit % before", "fit % after"]]
    for name in result.before.rmse:
        for label, b, a in rows_of:
            if name in b.rmse and name in a.rmse:
                rows.append([name, label, _num(b.rmse[name], ".4g"), _num(a.rmse[name], ".4g"),
                             _num(b.fit_percent.get(name), ".2f"), _num(a.fit_percent.get(name), ".2f")])
    rows.append(["BIC", "", _num(result.before.bic, ".1f"), _num(result.after.bic, ".1f"), "", ""])
    return _table(rows, {2, 3, 4, 5})


def _step_line(step) -> str:
    params = ", ".join(f"{p.name} = {p.value:.4g} ± {p.stderr:.2g}" if p.stderr else f"{p.name} = {p.value:.4g}"
                       for p in step.parameters)
    where = step.equation if step.equation.startswith("output") else f"d{step.equation}/dt"
    scored = "output" if step.evidence.scored_on != "equations" else "equation"
    return (f"{INDENT}+ {step.effect} in {where}: {step.term}  [{params}]  explains "
            f"{100 * step.evidence.explained_variance:.0f} % of the {scored} residual, BIC "
            f"-{step.evidence.bic_drop:.0f}" + ("  (specific to this record)" if step.record_specific else ""))


def discovery_report(result: "DiscoveryResult") -> str:
    """The text report of a discovery: conclusion, before/after table, steps, rejections, final fit."""
    lines = ["[[Discovery]]", f"{INDENT}conclusion: {result.conclusion}",
             f"{INDENT}wall time:  {result.wall_time_s:.1f} s" + ("  (time budget spent)" if result.budget_exhausted
                                                                else "")]
    if not result.before.success:
        lines.append(f"{INDENT}the declared model's fit was {result.before.status} (not good)")
    lines += _discovery_table(result)
    lines += ["[[Added terms]]"] + ([_step_line(s) for s in result.steps] or [f"{INDENT}none"])
    if result.rejected:
        lines += ["[[Not kept]]"] + [f"{INDENT}- {r.effect} ({r.term}): {r.reason}: {r.detail}"
                                      for r in result.rejected]
    if result.notes:
        lines += ["[[Notes]]"] + [f"{INDENT}{n}" for n in result.notes]
    lhs = "{}[k+1]" if result.model.discrete is not None else "d{}/dt"
    lines += ["[[Final model]]"] + [f"{INDENT}{lhs.format(s)} = {e}" for s, e in result.model.equations.items()]
    return "\n".join(lines) + "\n" + fit_report(result.fit)


def simulate_report(result: "SimulateResult") -> str:
    """The text report of a simulation: parameters used, initial states, metrics where measured."""
    lines = ["[[Simulation]]", f"{INDENT}wall time: {result.wall_time_s:.2f} s", "[[Parameters used]]"]
    lines += _table([["name", "value"]] + [[k, f"{v:.6g}"] for k, v in result.parameters.items()], {1})
    rows = [["record", "samples", "initial state", "from"]]
    for e in result.experiments:
        x0 = ", ".join(f"{k} = {v:.4g}" for k, v in e.initial_state.items())
        rows.append([e.name, str(len(e.time)), x0, e.initial_state_source])
    lines += ["[[Records]]"] + _table(rows, {1})
    if result.validation is not None:
        v = result.validation
        rows = [["output", "fit %", "NRMSE", "RMSE"]]
        rows += [[o, _num(v.fit_percent.get(o), ".2f"), _num(v.nrmse.get(o), ".4f"), _num(r, ".4g")]
                 for o, r in v.rmse.items()]
        lines += ["[[Against the measured outputs]]"] + _table(rows, {1, 2, 3})
    return "\n".join(lines)


def design_report(result: "DesignResult") -> str:
    """The text report of an experiment design: the signal, predicted errors or discrimination, baseline."""
    exp = result.experiment
    lines = ["[[Experiment design]]", f"{INDENT}criterion: {result.criterion}-optimal",
             f"{INDENT}samples: {len(exp.time)} over {exp.time[-1] - exp.time[0]:.6g} s",
             f"{INDENT}objective: {_num(result.objective)} (baseline {_num(result.objective_baseline)})",
             f"{INDENT}optimiser: {result.status}, {result.iterations} iterations, "
             f"wall time {result.wall_time_s:.2f} s"]
    if result.improvement is not None:
        lines.append(f"{INDENT}improvement over the baseline: {result.improvement:.3g}x")
    if result.parameters:
        rows = [["parameter", "value", "stderr (design)", "stderr (baseline)"]]
        rows += [[k, _num(v.value), _num(v.stderr, ".4g"), _num(v.stderr_baseline, ".4g")]
                 for k, v in result.parameters.items()]
        lines += ["[[Predicted standard errors]]"] + _table(rows, {1, 2, 3})
    if result.discrimination:
        rows = [["truth", "rival", "divergence", "baseline", "expected ΔBIC"]]
        rows += [[d.truth, d.rival, _num(d.divergence, ".4g"), _num(d.divergence_baseline, ".4g"),
                  _num(d.expected_delta_bic, ".4g")] for d in result.discrimination]
        lines += ["[[Discrimination]]"] + _table(rows, {2, 3, 4})
        closest = min(result.discrimination, key=lambda d: d.expected_delta_bic)
        if closest.settle_probability is not None:
            more = ("" if closest.duration_to_settle is None else
                    f"; about {closest.duration_to_settle:.3g} s at this amplitude would make it 0.9 (design again "
                    "with that duration)")
            lines.append(f"{INDENT}the closest pair ({closest.truth} vs {closest.rival}) is settled (ΔBIC > 10) "
                         f"with probability {closest.settle_probability:.2f}{more}")
    lines += [f"{INDENT}note: {n}" for n in result.notes]
    return "\n".join(lines)
