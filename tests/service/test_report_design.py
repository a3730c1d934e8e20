"""The report of an experiment design (issue 44): the designed input, the predicted outputs and each
rival's imitation, read from the figures' own line data against an independent simulation."""
import numpy as np
import pytest

from greyfit.schemas.design import DesignRequest
from greyfit.schemas.report import ReportRequest
from greyfit.schemas.simulate import SimulateRequest
from greyfit.service.http.openapi_examples import msd_design
from greyfit.solvers.design import design_experiment
from greyfit.solvers.simulation.simulate import simulate_request
from tests.service.test_report_figures import RecordingPyplot


@pytest.fixture
def plt():
    pytest.importorskip("matplotlib")
    return RecordingPyplot()


def _lines(fig) -> dict[str, np.ndarray]:
    return {line.get_label(): np.asarray(line.get_ydata(), dtype=float) for ax in fig.axes for line in ax.lines}


def test_the_input_figure_draws_the_designed_input_and_the_baseline(plt):
    from greyfit.service.report.design import input_figure
    request = DesignRequest.model_validate(msd_design())
    result = design_experiment(request)
    input_figure(plt, result, request, False, [])
    lines = _lines(plt.figures[-1])
    np.testing.assert_array_equal(lines["designed"], np.asarray(result.experiment.inputs["u"]))
    np.testing.assert_array_equal(lines["baseline"], np.ones(101))
    # the limits the request gave, drawn as the two horizontal lines
    flat = sorted({float(v[0]) for k, v in lines.items() if k.startswith("_") and np.ptp(v) == 0})
    assert flat == [-1.0, 1.0]


def _rival_design() -> dict:
    """A damper whose law is linear (the model) or quadratic (the rival): T-optimal, small."""
    model = {"name": "linear", "states": ["x", "v"], "inputs": ["u"],
             "parameters": [{"name": "c", "value": 0.8, "lower": 0, "upper": 10},
                            {"name": "k", "value": 5.0, "lower": 0, "upper": 50}],
             "equations": {"x": "v", "v": "u - c*v - k*x"}, "outputs": {"y": "x"}}
    rival = {**model, "name": "quadratic", "equations": {"x": "v", "v": "u - c*v*abs(v) - k*x"}}
    return {"model": model, "criterion": "T", "rivals": [{"name": "quadratic", "model": rival}],
            "inputs": {"u": {"lower": -1.0, "upper": 1.0}}, "outputs": {"y": 0.01}, "duration": 6.0,
            "sample_time": 0.1, "hold": 0.5, "initial_state": {"x": 0.0, "v": 0.0},
            "options": {"starts": 1, "rounds": 1, "max_iterations": 30}}


def test_the_outputs_figure_draws_the_model_and_the_rival_s_best_imitation(plt):
    from greyfit.service.report.design import output_figure
    request = DesignRequest.model_validate(_rival_design())
    result = design_experiment(request)
    output_figure(plt, result, request, False, [])
    lines = _lines(plt.figures[-1])
    record = result.experiment.model_dump()
    truth = simulate_request(SimulateRequest.model_validate(
        {"model": _rival_design()["model"], "experiments": [record]})).experiments[0].outputs["y"]
    np.testing.assert_allclose(lines["linear (predicted)"], truth, rtol=1e-9, atol=1e-12)
    pair = next(d for d in result.discrimination if d.truth == "linear")
    imitation = simulate_request(SimulateRequest.model_validate(
        {"model": _rival_design()["rivals"][0]["model"], "parameters": pair.rival_parameters,
         "experiments": [record]})).experiments[0].outputs["y"]
    label = next(k for k in lines if k.startswith("quadratic"))
    np.testing.assert_allclose(lines[label], imitation, rtol=1e-9, atol=1e-12)
    # what the curves show is the divergence the table states: Σ((y − ŷ)/σ)²
    gap = float(np.sum(((np.asarray(truth) - np.asarray(imitation)) / 0.01) ** 2))
    assert gap == pytest.approx(pair.divergence, rel=0.05)


def test_the_page_states_the_predicted_gain_and_a_mismatched_request_is_refused():
    pytest.importorskip("matplotlib")
    from greyfit.service.report.page import build_report
    request = DesignRequest.model_validate(msd_design())
    result = design_experiment(request)
    report = build_report(ReportRequest(result=result, request=request))
    assert [f.name for f in report.figures] == ["design_input", "design_outputs"]
    for name in ("c", "k"):
        p = result.parameters[name]
        assert f"{p.stderr:.4g}" in report.summary_html and f"{p.stderr_baseline:.4g}" in report.summary_html
    with pytest.raises(ValueError, match="request"):
        ReportRequest.model_validate({"result": result.model_dump(), "request": {
            "model": request.model.model_dump(), "experiments": [result.experiment.model_dump()]}})


def test_a_design_job_s_report_page_and_the_report_route(client):
    body = msd_design()
    page = client.post("/v1/report", json={"result": client.post("/v1/designs", json=body).json(), "request": body})
    assert page.status_code == 200, page.text
    assert 'id="fig-design_input"' in page.text and 'id="fig-design_outputs"' in page.text


def test_the_discovery_page_gives_the_design_request_of_an_ambiguous_step():
    """The page hands over the body the step carries, as JSON that validates as a DesignRequest."""
    import html
    import json
    import re
    from types import SimpleNamespace

    from greyfit.service.report.html import _next_experiment
    body = _rival_design()
    step = SimpleNamespace(effect="quadratic_drag", equation="v", design=body)
    page = _next_experiment(SimpleNamespace(steps=[SimpleNamespace(effect="offset", equation="x", design=None), step]))
    assert page.count("<li>") == 1 and "against quadratic" in page
    shown = html.unescape(re.search(r"<pre class='design-request'>(.*)</pre>", page, re.S).group(1))
    assert DesignRequest.model_validate(json.loads(shown)) == DesignRequest.model_validate(body)
    assert _next_experiment(SimpleNamespace(steps=[])) == ""
