"""Effects the old library had no family for, on the procedural generator (bench/discovery_generator.py):
a dead zone on the input and Monod kinetics (a saturable rate), named with the declared parameters
right; and a sign law (Coulomb friction) never offered on a positive quantity. One seed each; the rates
over many seeds are `bench/bench_discovery_suite.py --generated out` (docs/discovery.md)."""
import numpy as np
import pytest

from bench.discovery_generator import generate
from greyfit.schemas.discovery import DiscoverRequest
from greyfit.solvers.discovery import discover
from greyfit.solvers.screening.families.base import changes_sign, keeps_positive


def _discover(group: str, seed: int):
    case = generate(group, seed)
    case.body["discovery"] = {"time_budget_s": 300}
    return case, discover(DiscoverRequest.model_validate(case.body))


def _worst_error(case, res) -> float:
    return max(abs(res.fit.parameters[k].value - v) / abs(v) for k, v in case.truth.items())


def test_a_positive_quantity_does_not_change_sign_a_velocity_does():
    t = np.linspace(0, 50, 1000)
    population = 2 * (1 - np.exp(-t)) - 0.01 * np.exp(-t)   # starts a hair below 0, as a fit may
    velocity = np.sin(t) * np.exp(-0.02 * t)
    assert not changes_sign([population]) and keeps_positive([population])
    assert changes_sign([velocity]) and not keeps_positive([velocity])


@pytest.mark.slow
def test_a_dead_zone_on_the_input_is_named_with_its_width_and_the_gain_right():
    # two tanks, the first fed through a dead zone of 0.7-1.0 over held levels 0.2-2
    case, res = _discover("out", 6)
    assert case.effect == "dead_zone"
    assert [(s.effect, s.equation) for s in res.steps] == [("dead_zone", case.equation)], res.conclusion
    assert _worst_error(case, res) < 0.05


@pytest.mark.slow
def test_monod_kinetics_is_a_saturable_rate_with_the_declared_rates_right():
    # two populations, the first consumed at a Monod rate -Vm·n1/(0.3 + n1) beside its declared -b1·n1
    case, res = _discover("out", 9)
    assert case.effect == "monod"
    assert [(s.effect, s.equation) for s in res.steps] == [("saturable_rate", case.equation)], res.conclusion
    assert _worst_error(case, res) < 0.05
    assert res.fit.parameters[f"K_{case.equation}"].value == pytest.approx(0.3, rel=0.2)
