"""Where a fit's time goes (`solver.timings`): the stopwatch's accounting on a clock the test
drives (a stage inside another counts for the inner one, the rest is "other"), and a real fit's
stages: every one present and in order, the solve and the checks non-zero, the watch gone after the
call. No assertion compares with the machine's clock."""
import numpy as np
import pytest

import greyfit
from greyfit.schemas.text_report import fit_report, timings_text
from greyfit.solvers import timing
from greyfit.solvers.timing import FIT_STAGES, Stopwatch
from tests.servers import msd_request
from tests.systems import MSD_TRUTH


class _Ticks:
    """perf_counter for the test: the time moves only when the test says so."""

    def __init__(self):
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_stopwatch_counts_a_nested_stage_for_the_inner_one_only(monkeypatch):
    ticks = _Ticks()
    monkeypatch.setattr(timing, "_now", ticks)
    watch = Stopwatch(("a", "b"))
    ticks.now += 1.0                # outside any stage: other
    with watch.stage("a"):
        ticks.now += 2.0
        with watch.stage("b"):
            ticks.now += 3.0
        ticks.now += 4.0
        with pytest.raises(ValueError), watch.stage("b"):   # a stage that raises still counts
            ticks.now += 0.5
            raise ValueError
    ticks.now += 0.25
    assert watch.report() == {"a": 6.0, "b": 3.5, "other": 1.25}
    assert sum(watch.report().values()) == watch.elapsed() == 10.75


def test_a_fit_reports_each_stage_it_passes_through():
    request = greyfit.FitRequest.model_validate({**msd_request(0), "method": "auto"})
    greyfit.fit(request)   # the model's functions built: the second call is a warm fit
    result = greyfit.fit(request)
    timings = result.solver.timings
    assert list(timings) == [*FIT_STAGES, "other"]
    assert all(v >= 0 for v in timings.values())
    assert timings["solve"] > 0 and timings["prepare"] > 0 and timings["checks_after"] > 0
    assert timings["validation"] == 0                      # no validation record
    assert timing._WATCH.get() is None                     # the fit's watch ends with the fit
    for name, true in MSD_TRUTH.items():   # the fit the stages timed is the right one (m is fixed at its truth)
        assert np.isclose(result.parameters[name].value, true, rtol=0.02)
    text = fit_report(result)
    assert "time:" in text and "solve" in text


def test_timings_text_names_the_stages_and_leaves_the_empty_ones_out():
    line = timings_text({"prepare": 0.0041, "checks_before": 0.0, "solve": 0.0283, "checks_after": 0.012,
                         "other": 0.00001})
    assert line == "44.4 ms: prepare 4.1, solve 28, checks after 12"
    assert timings_text({"solve": 2.5, "prepare": 0.4}) == "2.9 s: solve 2.5, prepare 0.4"
