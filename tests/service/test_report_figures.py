"""What the report's figures draw, read from the matplotlib figures themselves (labels, line data).

`RecordingPyplot` hands the figure functions pyplot and keeps every figure they make, so a test can
read the axes' labels and the lines' data after the PNG is written.
"""
import json
from pathlib import Path

import numpy as np
import pytest

from greyfit.schemas.fit import FitRequest
from greyfit.service.report_html import summary_html
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
    from greyfit.service.report import parameter_figure
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
