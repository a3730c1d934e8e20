"""What the HTML report says: the verdict, the tables, frequency requests, the discrepancy figure.

Fits are real (the mass-spring-damper example, variants of it, a frequency fit of two PI loops);
the page's text is checked, the browser test (test_report_browser.py) checks that it renders.
"""
import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from greyfit.schemas.fit import FitRequest, FitResult
from greyfit.schemas.report import ReportRequest
from greyfit.service.report.html import summary_html
from greyfit.solvers.fit import fit_model
from tests.frequency_systems import TRUTH, frequency_data, seed001_model

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = json.loads((ROOT / "examples" / "msd_request.json").read_text())


def fit_of(change=None) -> tuple[dict, FitResult]:
    body = json.loads(json.dumps(EXAMPLE))
    if change is not None:
        change(body)
    return body, fit_model(FitRequest.model_validate(body))


def product_of_dampings(body):
    body["model"]["parameters"].append({"name": "c2", "value": 1.0, "lower": 0.1})
    body["model"]["equations"]["v"] = "(u - c*c2*v - k*x)/m"


def test_a_converged_suspect_fit_is_not_called_not_converged():
    """The header was keyed on `success`, which is false for every suspect result."""
    _, result = fit_of(product_of_dampings)
    assert result.quality == "suspect" and result.success is False
    assert result.solver.return_status == "Solve_Succeeded"
    page = summary_html(result, None, result.model)
    assert 'data-converged="true"' in page and 'data-quality="suspect"' in page
    assert "not converged" not in page
    for code in {w.code for w in result.warnings}:
        assert f"<code>{code}</code>" in page   # every warning listed with its code


def test_a_fit_stopped_at_max_iter_is_not_converged_and_failed():
    _, result = fit_of(lambda b: b.setdefault("options", {}).update(max_iter=1))
    page = summary_html(result, None, result.model)
    assert "<b>not converged</b>" in page and 'data-quality="failed"' in page


def test_tables_carry_units_equations_version_and_date():
    from greyfit import __version__
    _, result = fit_of()
    page = summary_html(result, None, result.model)
    c = result.parameters["c"]
    assert (f"<td>c</td><td>{c.value:.6g}</td><td>{c.stderr:.3g}</td>" in page
            and f"[{c.ci95[0]:.6g}, {c.ci95[1]:.6g}]</td><td>N s/m</td><td>0.3</td>" in page)
    assert "dv/dt = (u - c*v - k*x)/m" in page and "units: x [m], v [m/s], u [N], t [s]" in page
    assert f"greyfit {__version__}" in page and " UTC</p>" in page
    for out in ("x", "v"):
        assert f"<td>{out}</td><td>estimation</td><td>{result.metrics.fit_percent[out]:.2f}</td>" in page


@pytest.fixture(scope="module")
def frequency_pair():
    pytest.importorskip("matplotlib")
    from greyfit.schemas.frequency import FrequencyFitRequest
    from greyfit.solvers.frequency import fit_frequency_response
    request = {"model": seed001_model({n: 1.5 * v for n, v in TRUTH.items()}),
               "data": [frequency_data(TRUTH, 1, 1, seed=4, name="pi")]}
    result = fit_frequency_response(FrequencyFitRequest.model_validate(request))
    return request, json.loads(result.model_dump_json())


def test_frequency_report_over_http_draws_bode_and_nyquist(client, frequency_pair):
    request, result = frequency_pair
    assert result["model"]["kind"] == "transfer_function"   # the result carries its model
    for body in ({"result": result, "request": request}, {"result": result}):
        resp = client.post("/v1/report", json=body)
        assert resp.status_code == 200, resp.text
        page = resp.text
        assert 'id="fig-bode"' in page and 'id="fig-nyquist"' in page
        assert 'id="fig-compare' not in page   # no time records to compare


def test_the_report_of_a_frequency_job_draws_from_its_stored_request(client, frequency_pair):
    from tests.service.conftest import wait_for_job
    request, _ = frequency_pair
    resp = client.post("/v1/frequency-fits/jobs", json={"requests": [request]})
    assert resp.status_code == 202, resp.text
    job = wait_for_job(client, resp.json()["id"])
    assert job["status"] == "succeeded", job
    page = client.get(f"/v1/jobs/{job['id']}/report")
    assert page.status_code == 200, page.text   # the stored request is a FrequencyFitRequest
    assert 'id="fig-bode"' in page.text and 'id="fig-nyquist"' in page.text


def test_a_bad_frequency_request_names_its_fields_not_union_internals(frequency_pair):
    from pydantic import ValidationError
    _, result = frequency_pair
    with pytest.raises(ValidationError) as err:
        ReportRequest.model_validate({"result": result, "request": {"model": {"kind": "transfer_function"},
                                                                     "data": []}})
    locs = [".".join(map(str, e["loc"])) for e in err.value.errors()]
    assert "request.frequency_fit.data" in locs, locs
    assert not [loc for loc in locs if "function-after" in loc or ".fit." in loc or "discover" in loc], locs


def test_discrepancy_is_drawn_against_its_variable_where_discovery_returns_it():
    """The field is added by the shape step of discovery; the figure reads it defensively."""
    plt = pytest.importorskip("matplotlib.pyplot")
    from greyfit.service.report.discovery import discrepancy_figure
    x = np.linspace(-1, 1, 200)
    equation = SimpleNamespace(equation="v", variable="x", variable_samples={"e1": x.tolist()},
                               samples={"e1": (20 * x ** 3 + 0.01 * np.sin(40 * x)).tolist()},
                               law_samples={"e1": (20 * x ** 3).tolist()}, law_grid=x.tolist(),
                               law_values=(20 * x ** 3).tolist(), share_explained=0.99)
    notes: list[str] = []
    figure = discrepancy_figure(plt, SimpleNamespace(discrepancy=SimpleNamespace(equations=[equation])), False, notes)
    assert figure is not None and figure.name == "discrepancy" and figure.png[:4] == b"\x89PNG" and not notes
    older = SimpleNamespace(**{k: v for k, v in vars(equation).items() if k not in ("law_grid", "law_values")})
    assert discrepancy_figure(plt, SimpleNamespace(discrepancy=SimpleNamespace(equations=[older])), False, notes)
    assert notes and "older version" in notes[0]   # its per-sample fit is not drawn as a line
    assert discrepancy_figure(plt, SimpleNamespace(), False, notes) is None             # an older result
    assert discrepancy_figure(plt, SimpleNamespace(discrepancy=None), False, notes) is None
    no_variable = SimpleNamespace(equations=[SimpleNamespace(equation="v", variable=None, variable_samples={})])
    assert discrepancy_figure(plt, SimpleNamespace(discrepancy=no_variable), False, notes) is None


def test_compare_keeps_both_lines_visible_at_a_98_percent_fit():
    """The measured line vanished under the simulated one; now it is a wide light band beneath."""
    import io
    pytest.importorskip("matplotlib")
    import matplotlib.image as mpimg
    import matplotlib.pyplot as plt

    from greyfit.service.report.page import Series, compare_figure
    t = np.linspace(0, 10, 201)
    simulated = np.sin(t)
    measured = simulated + 0.02 * np.random.default_rng(0).standard_normal(t.size)   # about 98 % fit
    figure = compare_figure(plt, [Series("e1", t, {"x": measured}, {"x": simulated})], "estimation",
                            units={"x": "m", "t": "s"})
    rgb = mpimg.imread(io.BytesIO(figure.png))[:, :, :3]

    def pixels(colour, tol):
        return int((np.abs(rgb - np.array(colour)).max(axis=2) < tol).sum())

    light, blue = pixels((0.72, 0.72, 0.72), 0.03), pixels((0.12, 0.47, 0.71), 0.08)
    assert blue > 300, blue                # the simulated line is drawn
    assert light > 2 * blue, (light, blue)  # and the measured one shows on both sides of it
