"""What the report's figures draw, read from the matplotlib figures themselves (labels, line data).

`RecordingPyplot` hands the figure functions pyplot and keeps every figure they make, so a test can
read the axes' labels and the lines' data after the PNG is written.
"""
import json
from pathlib import Path

import numpy as np
import pytest

from greyfit.schemas.fit import FitRequest
from greyfit.service.report.html import summary_html
from greyfit.solvers.fit import fit_model

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = json.loads((ROOT / "examples" / "msd_request.json").read_text())


class RecordingPyplot:
    """pyplot, keeping each figure `subplots` makes (closing a figure leaves it readable)."""

    def __init__(self):
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
        self._plt, self.figures = plt, []

    def subplots(self, *args, **kwargs):
        fig, axes = self._plt.subplots(*args, **kwargs)
        self.figures.append(fig)
        return fig, axes

    def __getattr__(self, name):
        return getattr(self._plt, name)


@pytest.fixture
def plt():
    pytest.importorskip("matplotlib")
    return RecordingPyplot()


def test_labels_give_the_confidence_level_the_fit_used(plt):
    """Every label said 95 % whatever options.confidence_level was."""
    from greyfit.service.report.page import parameter_figure
    body = json.loads(json.dumps(EXAMPLE))
    body.setdefault("options", {})["confidence_level"] = 0.9
    result = fit_model(FitRequest.model_validate(body))
    assert result.confidence_level == 0.9
    c = result.parameters["c"]
    # the interval is the 90 % one: ± t(0.95, ν) stderr, t ≈ 1.65 with hundreds of degrees of freedom
    assert (c.ci95[1] - c.ci95[0]) / (2 * c.stderr) == pytest.approx(1.65, abs=0.01)
    assert json.loads(result.model_dump_json())["confidence_level"] == 0.9

    text = result.report()
    assert "90 % CI" in text and "at the 90 % confidence level" in text and "95 %" not in text
    page = summary_html(result, None, result.model)
    assert "<th>90 % CI</th>" in page and "95 %" not in page
    figure = parameter_figure(plt, result)
    assert "90 % confidence intervals" in figure.title and "95 %" not in figure.title
    assert plt.figures[-1].axes[0].get_xlabel() == "90 % confidence interval [% of the estimate]"


def test_an_older_result_without_the_level_reads_as_95_percent():
    result = fit_model(FitRequest.model_validate(EXAMPLE))
    older = json.loads(result.model_dump_json())
    del older["confidence_level"]
    assert type(result).model_validate(older).confidence_level == 0.95
    assert "95 % CI" in result.report()


def lightly_damped_fit():
    """G = b0 / (s² + a1 s + a0), ω_n = 10 rad/s, ζ = 0.02, measured at 24 frequencies none of which
    is within 2 % of the resonance (its half-power band is ±2 %)."""
    from greyfit.schemas.frequency import FrequencyFitRequest
    from greyfit.solvers.frequency import fit_frequency_response
    omega = np.geomspace(0.4, 200, 24)
    s = 1j * omega
    g = 100 / (s ** 2 + 0.4 * s + 100) * (1 + 0.01 * np.random.default_rng(0).standard_normal(omega.size))
    request = {"model": {"kind": "transfer_function", "name": "resonance",
                         "parameters": [{"name": "b0", "value": 80, "lower": 0},
                                        {"name": "a1", "value": 0.6, "lower": 0},
                                        {"name": "a0", "value": 90, "lower": 0}],
                         "numerator": ["b0"], "denominator": ["1", "a1", "a0"]},
               "data": [{"name": "sweep", "omega": omega.tolist(), "real": g.real.tolist(), "imag": g.imag.tolist()}],
               "options": {"confidence_level": 0.9}}
    return fit_frequency_response(FrequencyFitRequest.model_validate(request))


def test_bode_and_nyquist_draw_the_model_through_its_resonance_not_a_chord(plt):
    from greyfit.service.report.frequency import frequency_figures, model_response
    result = lightly_damped_fit()
    assert result.quality == "good" and result.confidence_level == 0.9   # the frequency fit records it too
    p = {k: v.value for k, v in result.parameters.items()}
    ds = result.frequency_response.data[0]
    omega = np.asarray(ds.omega)

    def fitted_model(w):   # the fitted model, evaluated here from its parameters
        return p["b0"] / ((1j * w) ** 2 + p["a1"] * 1j * w + p["a0"])

    resonance = np.sqrt(p["a0"])
    assert np.min(np.abs(omega / resonance - 1)) > 0.02   # no data point on the peak
    peak = abs(fitted_model(resonance))
    assert peak > 1.4 * np.max(np.abs(fitted_model(omega)))   # drawn at the data alone, the peak is cut

    w, g = model_response(ds)
    assert w.size >= 10 * omega.size and np.all(np.diff(w) > 0)
    assert w[0] < omega[0] and w[-1] > omega[-1]
    np.testing.assert_allclose(g, fitted_model(w), rtol=1e-9)
    at = np.argmin(np.abs(w - resonance))
    assert w[at] == pytest.approx(resonance, rel=1e-9) and abs(g[at]) == pytest.approx(peak, rel=1e-9)
    assert np.all(np.isin(omega, w))   # and through the fitted values at the data

    notes: list[str] = []
    figures = frequency_figures(plt, result.frequency_response, False, notes)
    assert [f.name for f in figures] == ["bode", "nyquist"] and not notes
    bode, nyquist = plt.figures[-2:]
    model_line = next(line for line in bode.axes[0].get_lines() if line.get_linestyle() == "-")
    assert model_line.get_xdata().size == w.size
    assert np.max(model_line.get_ydata()) == pytest.approx(20 * np.log10(peak), abs=1e-6)
    curve = next(line for line in nyquist.axes[0].get_lines() if line.get_label() == "model")
    np.testing.assert_allclose(curve.get_xdata() + 1j * curve.get_ydata(), fitted_model(w), rtol=1e-9)


@pytest.fixture(scope="module")
def duffing_discovery():
    """A real discovery: Duffing measured in position, declared without its cubic spring (401 samples)."""
    from greyfit.schemas.discovery import DiscoverRequest
    from greyfit.solvers.discovery import discover
    from tests import coloured_records as cr
    from tests import partial_systems as ps
    body = {"model": ps.duffing_model(), "experiments": [cr.duffing_record(401, 1)], "method": "multiple_shooting"}
    body["model"]["units"] = {"y": "m", "yd": "m/s", "u": "N", "t": "s"}
    request = DiscoverRequest.model_validate(body)
    return request, discover(request)


def sign_changes(values: np.ndarray, tol: float) -> int:
    signs = np.sign(values[np.abs(values) > tol])
    return int(np.sum(signs[1:] != signs[:-1]))


def test_the_discrepancy_figure_draws_the_smooth_law_of_its_variable_not_a_sawtooth(plt, duffing_discovery):
    """The line was the fit at the samples (the law plus terms in the other states), sorted by the
    variable: a sawtooth. It is now the law on a grid of the variable."""
    from greyfit.service.report.discovery import discrepancy_figure
    from tests import partial_systems as ps
    _, result = duffing_discovery
    assert [s.effect for s in result.steps] == ["cubic_stiffness"], result.conclusion
    eq = result.discrepancy.equations[0]
    assert eq.equation == "yd" and eq.variable == "y"
    x = np.array(eq.variable_samples["est"])
    grid, law = np.array(eq.law_grid), np.array(eq.law_values)
    assert grid.size == law.size == 200 and np.all(np.diff(grid) > 0)
    assert grid[0] == pytest.approx(x.min()) and grid[-1] == pytest.approx(x.max())

    notes: list[str] = []
    figure = discrepancy_figure(plt, result, False, notes)
    assert figure is not None and not notes
    line = next(ln for ln in plt.figures[-1].axes[0].get_lines() if ln.get_label() == "fitted smooth law")
    np.testing.assert_array_equal(line.get_xdata(), grid)
    np.testing.assert_array_equal(line.get_ydata(), law)
    tol = 1e-9 * np.ptp(law)
    # smooth: a cubic bends one way then the other (one inflection); the spline may add a wobble or two
    assert sign_changes(np.diff(law, 2), tol) <= 3
    sorted_fit = np.array(eq.law_samples["est"])[np.argsort(x)]
    assert sign_changes(np.diff(sorted_fit, 2), tol) > 100   # what was drawn before
    # and it is the missing term: -k3/m y³, plus the linear part the fitted k took up
    cubic = np.polyfit(grid, law, 3)
    assert cubic[0] == pytest.approx(-ps.DUFFING_TRUTH["k3"] / ps.DUFFING_TRUTH["m"], rel=0.1)
    assert np.sqrt(np.mean((law - np.polyval(cubic, grid)) ** 2)) < 0.02 * np.ptp(law)


def test_the_discrepancy_points_are_partial_residuals_that_scatter_about_the_law_by_the_fit_residual(
        plt, duffing_discovery):
    """Raw d against one variable strays from the curve by the linear terms in the other variables
    (held at their means on the curve): the points drawn are d less those terms, so they scatter about
    the curve by exactly the fit's residual (a GAM term plot's partial residuals)."""
    from greyfit.service.report.discovery import discrepancy_figure
    _, result = duffing_discovery
    eq = result.discrepancy.equations[0]
    x, d = np.array(eq.variable_samples["est"]), np.array(eq.samples["est"])
    fitted, grid, law = np.array(eq.law_samples["est"]), np.array(eq.law_grid), np.array(eq.law_values)
    notes: list[str] = []
    assert discrepancy_figure(plt, result, False, notes) is not None and not notes
    points = next(ln for ln in plt.figures[-1].axes[0].get_lines() if ln.get_label().startswith("d,"))
    np.testing.assert_allclose(points.get_xdata(), x)
    about_curve = np.asarray(points.get_ydata()) - np.interp(x, grid, law)
    np.testing.assert_allclose(about_curve, d - fitted, atol=1e-12 * np.ptp(d))
    raw_about_curve = d - np.interp(x, grid, law)
    # the other variables' terms lie in the fit's column space, orthogonal to its residual: never wider
    assert np.std(about_curve) <= np.std(raw_about_curve) * (1 + 1e-3)


def test_the_discovery_overlay_keeps_the_measured_line_visible_and_its_axes_carry_units(plt, duffing_discovery):
    """The measured line was thin grey under two model lines; now it is drawn as the compare figure
    draws it (wide and light, underneath), and the axes name the model's units."""
    import io

    import matplotlib.image as mpimg

    from greyfit.service.report.discovery import discovery_figures
    request, result = duffing_discovery
    figures, notes = discovery_figures(plt, result, request)
    assert [f.name for f in figures] == ["discovery_metrics", "discrepancy", "discovery_overlay"], notes
    overlay = plt.figures[-1]
    ax = overlay.axes[0]
    measured, without, final = ax.get_lines()
    assert measured.get_label() == "measured"
    assert measured.get_linewidth() > 2.5 * max(without.get_linewidth(), final.get_linewidth())
    assert measured.get_zorder() < min(without.get_zorder(), final.get_zorder())
    assert ax.get_ylabel() == "y [m]" and ax.get_xlabel() == "t [s]"
    assert plt.figures[-2].axes[0].get_xlabel() == "y [m]"   # d against y, in y's unit

    rgb = mpimg.imread(io.BytesIO(figures[-1].png))[:, :, :3]
    light = int((np.abs(rgb - 0.72).max(axis=2) < 0.03).sum())
    blue = int((np.abs(rgb - np.array((0.12, 0.47, 0.71))).max(axis=2) < 0.08).sum())
    assert blue > 300 and light > blue, (light, blue)   # the measured line shows beside the final model's


def test_the_residual_against_time_is_measured_minus_simulated_per_output(plt):
    """The figure beside the correlations (SITB's resid): its lines are the fit's own residuals,
    re-simulated from the request, with the sign y - ŷ."""
    from greyfit.service.report.page import estimation_series
    from greyfit.service.report.residuals import residual_time_figure
    body = json.loads(json.dumps(EXAMPLE))
    body.setdefault("options", {})["return_traces"] = True
    result = fit_model(FitRequest.model_validate(body))
    est, _ = estimation_series(result, FitRequest.model_validate(body), result.model)
    figure = residual_time_figure(plt, [("estimation", r) for r in est], units=dict(result.model.units))
    assert figure.name == "residuals_time"
    axes = plt.figures[-1].axes
    assert [ax.get_ylabel() for ax in axes] == ["e(v) [m/s]", "e(x) [m]"] and axes[-1].get_xlabel() == "t [s]"
    for ax, out in zip(axes, ("v", "x")):
        line = ax.get_lines()[-1]
        solver = np.array(result.traces[0].residuals[out], dtype=float)   # simulated - measured
        assert np.allclose(line.get_ydata(), -solver, atol=1e-9)
        rms = float(np.sqrt(np.mean(solver ** 2)))
        assert rms == pytest.approx(result.metrics.rmse[out], rel=1e-9)


def test_the_profile_curves_cross_the_threshold_at_the_interval_ends(plt):
    from greyfit.service.report.residuals import profile_figure
    body = json.loads(json.dumps(EXAMPLE))
    body.setdefault("options", {})["profile"] = ["c"]
    result = fit_model(FitRequest.model_validate(body))
    profile = result.profile["c"]
    figure = profile_figure(plt, result)
    assert figure.name == "profiles"
    ax = plt.figures[-1].axes[0]
    assert ax.get_xlabel() == "c [N s/m]"
    curve = ax.get_lines()[0]
    values, costs = np.asarray(curve.get_xdata()), np.asarray(curve.get_ydata())
    assert np.allclose(values, profile.values)
    ends = sorted(float(line.get_xdata()[0]) for line in ax.get_lines()[2:4])
    assert ends == pytest.approx([profile.lower, profile.upper])
    # the interval holds the estimate, and the profile is below the threshold inside it
    inside = (values > profile.lower) & (values < profile.upper)
    assert profile.lower < result.parameters["c"].value < profile.upper
    assert inside.any() and (costs[inside] <= profile.threshold * (1 + 1e-9)).all()


def test_the_discovery_page_gives_each_rejection_its_reason_and_detail(duffing_discovery):
    """It said "evidence" alone; the result's detail (the numbers that decided) is on the page now."""
    import html

    from greyfit.schemas.discovery import RejectedCandidate
    _, result = duffing_discovery
    rejected = RejectedCandidate(effect="coulomb_friction", equation="yd", term="Fc*tanh(yd/0.01)", reason="evidence",
                                 detail="the refit lowered BIC by 1.3 only (t = 0.8)")
    result = result.model_copy(update={"rejected": [*result.rejected, rejected]})
    page = html.unescape(summary_html(result.fit, result, result.model)).replace("<b>", "").replace("</b>", "")
    for r in result.rejected:
        assert f"{r.reason}: {r.detail}" in page


def test_the_discovery_validation_overlay_shows_the_added_term_on_a_record_the_fit_never_saw(plt, duffing_discovery):
    """A second Duffing record (another input) as validation: the final model follows it closer than
    the same model without its added terms."""
    from greyfit.schemas.discovery import DiscoverRequest
    from greyfit.service.report.discovery import discovery_figures
    from tests import coloured_records as cr
    request, result = duffing_discovery
    body = request.model_dump(mode="json", exclude_unset=True)
    body["validation"] = [cr.duffing_record(401, 2, name="val")]
    figures, notes = discovery_figures(plt, result, DiscoverRequest.model_validate(body))
    assert [f.name for f in figures][-2:] == ["discovery_overlay", "discovery_validation_overlay"], notes
    ax = plt.figures[-1].axes[0]
    measured, without, final = (np.asarray(line.get_ydata()) for line in ax.get_lines())
    rms = [float(np.sqrt(np.mean((y - measured) ** 2))) for y in (without, final)]
    assert rms[1] < 0.5 * rms[0], rms
    assert ax.get_ylabel() == "y [m]"


def test_the_added_parameter_carries_the_unit_its_equation_implies(duffing_discovery):
    """The cubic spring added to dyd/dt = (u - ...)/m sits beside u [N]: its coefficient is in N/m^3,
    on the step, the final fit, the final model and the page."""
    _, result = duffing_discovery
    step = result.steps[0]
    assert step.effect == "cubic_stiffness"
    name = step.parameters[0].name
    assert step.parameters[0].unit == "N/m^3"
    assert result.fit.parameters[name].unit == "N/m^3"
    assert {p.name: p.unit for p in result.model.parameters}[name] == "N/m^3"
    assert "<td>N/m^3</td>" in summary_html(result.fit, result, result.model)
