"""The discovery loop on records shaped like users' data: measurement noise that is not white (a
sensor's first-order low-pass at 0.15 of Nyquist, AR(1) drift with coefficient 0.9) and inputs held
between samples by a digital controller (zero-order hold). Outputs only (positions), truth simulated
with scipy (tests/coloured_records.py). Complete models must get nothing; an undeclared effect must
still be found with its parameters near the truth. The false-positive rates over many more seeds are
in bench/bench_discovery_noise.py."""
import numpy as np
import pytest

from greyfit.schemas.discovery import DiscoverRequest
from greyfit.solvers.discovery import discover
from tests import coloured_records as cr
from tests import partial_systems as ps

COULOMB = 0.5


def coulomb_force(x, v):
    return COULOMB * np.tanh(v / 1e-3)


def run(model: dict, experiment: dict, **options) -> object:
    body = {"model": model, "experiments": [experiment], "method": "multiple_shooting", "options": options}
    return discover(DiscoverRequest.model_validate(body))


def complete_record(system: str, seed: int, kind: str) -> tuple[dict, dict]:
    # short records: what is tested here is the decision (nothing added), over many seeds
    if system == "msd":
        return cr.msd_position_model(), cr.msd_record(501, seed, kind)
    return cr.duffing_complete_model(), cr.duffing_record(401, seed, kind)


@pytest.mark.parametrize("system", ["msd", "duffing"])
@pytest.mark.parametrize("kind", ["lowpass", "ar1"])
def test_complete_models_under_coloured_noise_get_nothing_added_over_two_seeds(system, kind):
    # the rate over many seeds (100 each) is bench/bench_discovery_noise.py's, in docs/discovery-loop.md
    for seed in range(2):
        model, record = complete_record(system, seed, kind)
        res = run(model, record)
        assert res.steps == [], (system, kind, seed, res.conclusion)
        assert res.model.equations == model["equations"]
        assert not res.budget_exhausted


@pytest.mark.parametrize("kind", ["lowpass", "ar1"])
def test_coulomb_friction_is_found_from_position_under_coloured_noise(kind):
    res = run(cr.msd_position_model(), cr.msd_record(751, 3, kind, extra_force=coulomb_force))
    assert [s.effect for s in res.steps] == ["coulomb"], (res.conclusion, res.rejected)
    p = res.fit.parameters
    assert res.steps[0].parameters[0].value == pytest.approx(COULOMB, rel=0.05)
    assert p["c"].value == pytest.approx(0.8, rel=0.05)
    assert p["k"].value == pytest.approx(5.0, rel=0.02)
    assert res.after.rmse["x"] < 0.3 * res.before.rmse["x"]


@pytest.mark.parametrize("kind", ["lowpass", "ar1"])
def test_undeclared_cubic_spring_is_found_under_coloured_noise(kind):
    res = run(ps.duffing_model(), cr.duffing_record(601, 4, kind))
    assert [s.effect for s in res.steps] == ["cubic_stiffness"], (res.conclusion, res.rejected)
    assert res.steps[0].parameters[0].value == pytest.approx(ps.DUFFING_TRUTH["k3"], rel=0.05)
    assert res.fit.parameters["k"].value == pytest.approx(ps.DUFFING_TRUTH["k"], rel=0.03)
    assert res.fit.parameters["d"].value == pytest.approx(ps.DUFFING_TRUTH["d"], rel=0.05)


def test_held_inputs_with_zoh_coulomb_found_and_complete_duffing_left_alone():
    """A digital controller's output, held between samples, declared as such (input_interpolation
    'zoh'): the friction is found with its parameters; the complete model gets nothing."""
    res = run(cr.msd_position_model(), cr.msd_record(751, 5, extra_force=coulomb_force, held=True),
              input_interpolation="zoh")
    assert [s.effect for s in res.steps] == ["coulomb"], (res.conclusion, res.rejected)
    assert res.steps[0].parameters[0].value == pytest.approx(COULOMB, rel=0.05)
    assert res.fit.parameters["c"].value == pytest.approx(0.8, rel=0.05)
    assert res.fit.parameters["k"].value == pytest.approx(5.0, rel=0.02)
    for seed in (6, 7):
        res = run(cr.duffing_complete_model(), cr.duffing_record(401, seed, held=True), input_interpolation="zoh")
        assert res.steps == [], (seed, res.conclusion)
        assert res.fit.parameters["k3"].value == pytest.approx(ps.DUFFING_TRUTH["k3"], rel=0.05)


def test_time_budget_ends_the_search_and_says_so():
    """A budget spent by the base fit: no screen or refit starts, the result says why."""
    body = {"model": ps.duffing_model(), "experiments": [cr.duffing_record(401, 1)],
            "method": "multiple_shooting", "discovery": {"time_budget_s": 1e-3}}
    res = discover(DiscoverRequest.model_validate(body))
    assert res.budget_exhausted and res.steps == []
    assert "time budget" in res.conclusion and any("time_budget_s" in n for n in res.notes)
    assert res.timings["base_fit"] > 0 and res.timings["screening"] == 0 and res.timings["refits"] == 0
