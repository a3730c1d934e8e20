"""The report of an experiment design: the designed input beside the one that was used, what the
model predicts on it (and, for a discrimination design, each rival's best imitation of it), and the
predicted gain as a table.

The input figure needs only the result; the predicted outputs need the model, so they are drawn
when the DesignRequest comes with the result (as `greyfit design --report` and the jobs' report
give it). The rivals' curves use the parameters the design refitted them to (`rival_parameters`):
what the eye sees between the curves is the divergence the table states.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from greyfit.schemas.design import DesignRequest, DesignResult
from greyfit.schemas.experiment import Experiment
from greyfit.schemas.model import Model
from greyfit.service.report.html import _e, _n, _table
from greyfit.service.report.page import Figure, _grid_layout, _save, _short, _with_unit

MAX_PANELS = 8


def _stairs(ax, time: list[float], values: list[Optional[float]], **style) -> None:
    """A held input as the staircase it is (each value kept until the next sample)."""
    t = np.asarray(time, dtype=float)
    v = np.asarray([np.nan if x is None else x for x in values], dtype=float)
    ax.step(t, v, where="post", **style)


def input_figure(plt, result: DesignResult, request: Optional[DesignRequest], svg: bool,
                 notes: list[str]) -> Figure:
    """Each input of the designed experiment against time, with its limits and the baseline's input.

    Parameters
    ----------
    plt : module
        matplotlib.pyplot (Agg).
    result : DesignResult
        The design.
    request : DesignRequest or None
        Its request: the limits and the baseline come from it.
    svg : bool
        Draw an SVG too.
    notes : list of str
        What could not be drawn is appended here.

    Returns
    -------
    Figure
        Named ``design_input``.
    """
    exp = result.experiment
    names = sorted(exp.inputs)
    if len(names) > MAX_PANELS:
        notes.append(f"design input: the first {MAX_PANELS} of {len(names)} inputs are drawn")
        names = names[:MAX_PANELS]
    units = dict(request.model.units) if request is not None and request.model is not None else {}
    fig, axes = plt.subplots(len(names), 1, figsize=(8.0, 2.2 * len(names) + 0.6), squeeze=False, sharex=True)
    for r, name in enumerate(names):
        ax = axes[r][0]
        _stairs(ax, exp.time, exp.inputs[name], color="C0", lw=1.4, label="designed")
        baseline = request.baseline if request is not None else None
        if baseline is not None and name in baseline.inputs:
            _stairs(ax, baseline.time, baseline.inputs[name], color="0.45", lw=1.0, ls="--", label="baseline")
        limits = request.inputs.get(name) if request is not None else None
        if limits is not None:
            for bound in (limits.lower, limits.upper):
                if bound is not None:
                    ax.axhline(bound, color="C3", lw=0.6, ls=":")
        ax.set_ylabel(_with_unit(_short(name), units, name))
        ax.legend(loc="upper right", fontsize=7, frameon=False)
    axes[-1][0].set_xlabel(_with_unit("t", units, "t"))
    _grid_layout(fig, len(names), 1, hgap=0.25)
    return _save(plt, fig, "design_input", "The designed input (limits dotted; the baseline's input dashed)", svg)


def _simulated(model: Model, values: dict[str, float], experiment: Experiment,
               fit_result=None) -> dict[str, np.ndarray]:
    from greyfit.schemas.simulate import SimulateRequest
    from greyfit.solvers.simulation.simulate import simulate_request
    body = SimulateRequest(model=model, parameters=values, fit_result=fit_result,
                           experiments=[experiment.model_copy(update={"outputs": {}})])
    sim = simulate_request(body).experiments[0]
    return {k: np.asarray([np.nan if v is None else v for v in vals], dtype=float) for k, vals in sim.outputs.items()}


def _rival_curves(result: DesignResult, request: DesignRequest, truth: str) -> list[tuple[str, dict]]:
    """Each rival's best imitation of `truth` on the designed input, with the parameters the design
    refitted it to."""
    rivals = {r.name: r.model for r in request.rivals}
    curves = []
    for pair in result.discrimination:
        if pair.truth == truth and pair.rival in rivals:
            curves.append((f"{pair.rival} (divergence {pair.divergence:.3g})",
                           _simulated(rivals[pair.rival], pair.rival_parameters, result.experiment)))
    return curves


def output_figure(plt, result: DesignResult, request: DesignRequest, svg: bool,
                  notes: list[str]) -> Optional[Figure]:
    """The model's predicted outputs on the designed input, with ±σ of the noise the request gives; for
    a discrimination design, each rival refitted to imitate it.

    Parameters
    ----------
    plt : module
        matplotlib.pyplot (Agg).
    result : DesignResult
        The design.
    request : DesignRequest
        Its request (the model, its values, the rivals, the outputs' noise).
    svg : bool
        Draw an SVG too.
    notes : list of str
        What could not be drawn is appended here.

    Returns
    -------
    Figure or None
        Named ``design_outputs``; None when the model cannot be simulated (the note says why).
    """
    model = request.model if request.model is not None else (
        request.fit_result.model if request.fit_result is not None else None)
    if not isinstance(model, Model):
        notes.append("no predicted outputs: the request carries no ODE model")
        return None
    try:
        main = _simulated(model, dict(request.parameters), result.experiment, request.fit_result)
        rivals = _rival_curves(result, request, model.name) if result.criterion == "T" else []
    except Exception as exc:   # noqa: BLE001 - a figure that cannot be drawn is a note, not a failed page
        notes.append(f"no predicted outputs: the model could not be simulated on the design ({exc})")
        return None
    outputs = [o for o in sorted(request.outputs) if o in main][:MAX_PANELS]
    t = np.asarray(result.experiment.time, dtype=float)
    fig, axes = plt.subplots(len(outputs), 1, figsize=(8.0, 2.4 * len(outputs) + 0.6), squeeze=False, sharex=True)
    for r, out in enumerate(outputs):
        ax = axes[r][0]
        sigma = request.outputs[out]
        ax.fill_between(t, main[out] - sigma, main[out] + sigma, color="C0", alpha=0.15, lw=0, label="±σ noise")
        ax.plot(t, main[out], color="C0", lw=1.4, label=f"{_short(model.name)} (predicted)")
        for k, (label, curve) in enumerate(rivals):
            if out in curve:
                ax.plot(t, curve[out], color=f"C{k + 1}", lw=1.0, ls="--", label=_short(label, 60))
        ax.set_ylabel(_with_unit(_short(out), dict(model.units), out))
        ax.legend(loc="upper right", fontsize=7, frameon=False)
    axes[-1][0].set_xlabel(_with_unit("t", dict(model.units), "t"))
    _grid_layout(fig, len(outputs), 1, hgap=0.25)
    title = ("Predicted outputs on the designed input, and each rival's best imitation" if rivals
             else "Predicted outputs on the designed input (±σ of the measurement noise)")
    return _save(plt, fig, "design_outputs", title, svg)


def design_html(result: DesignResult) -> str:
    """The verdict line and the predicted gain: standard errors (D, A, E) or divergences (T), each
    beside the baseline's where one was given.

    Parameters
    ----------
    result : DesignResult
        The design.

    Returns
    -------
    str
        HTML (cells escaped).
    """
    gain = "" if result.improvement is None else f", predicted gain over the baseline <b>{result.improvement:.3g}×</b>"
    head = (f'<p class="verdict" data-criterion="{_e(result.criterion)}">criterion <b>{_e(result.criterion)}</b>, '
            f"Ipopt {_e(result.status)} after {result.iterations} iterations{gain}</p>")
    if result.criterion == "T":
        rows = [[_e(d.truth), _e(d.rival), _n(d.divergence, ".4g"), _n(d.divergence_baseline, ".4g"),
                 _n(d.expected_delta_bic, ".4g"), _n(d.expected_delta_bic_baseline, ".4g"),
                 _n(d.settle_probability, ".2f"), _n(d.duration_to_settle, ".3g")]
                for d in result.discrimination]
        table = _table("discrimination", ["truth", "rival", "divergence", "baseline", "expected ΔBIC",
                                          "baseline ΔBIC", "P(settled)", "duration for 0.9 [s]"], rows)
    else:
        rows = []
        for name, p in result.parameters.items():
            ratio = (p.stderr_baseline / p.stderr) if p.stderr and p.stderr_baseline else None
            rows.append([_e(name), _n(p.value), _n(p.stderr, ".4g"), _n(p.stderr_baseline, ".4g"),
                         _n(ratio, ".3g")])
        table = _table("predicted", ["parameter", "value", "predicted stderr", "baseline stderr",
                                     "baseline / designed"], rows)
    notes = "".join(f"<li>{_e(n)}</li>" for n in result.notes)
    return f"{head}<h2>Predicted</h2>{table}" + (f"<ul class='design-notes'>{notes}</ul>" if notes else "")


def design_report(result: DesignResult, request: Optional[DesignRequest], title: Optional[str], svg: bool):
    """The page of a design: its input, the predicted outputs (with the request), the predicted gain.

    Parameters
    ----------
    result : DesignResult
        The design.
    request : DesignRequest or None
        Its request; without it the outputs are not drawn (a note says so).
    title : str or None
        The page's title.
    svg : bool
        Draw SVGs too.

    Returns
    -------
    Report
        Figures ``design_input`` and (with the request) ``design_outputs``.
    """
    from greyfit.service.report.page import Report, _pyplot
    plt = _pyplot()
    report = Report(title=title or "greyfit experiment design")
    report.figures.append(input_figure(plt, result, request, svg, report.notes))
    if request is None:
        report.notes.append("no predicted outputs: give the DesignRequest with the result")
    else:
        figure = output_figure(plt, result, request, svg, report.notes)
        if figure is not None:
            report.figures.append(figure)
    report.summary_html = design_html(result)
    return report
