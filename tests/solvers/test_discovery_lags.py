"""Unmodelled first-order dynamics (families/lags.py): a sensor lag, an actuator lag, an extra pole
between two states. Truth simulated exactly with the lag (tests/lag_systems.py), the model declared
without it: the fit's lack-of-fit screen names a lag, discovery adds the right one and estimates its
time constant; right models are not flagged."""
import numpy as np
import pytest

from greyfit.schemas.discovery import DiscoverRequest
from greyfit.schemas.fit import FitRequest
from greyfit.schemas.model import Model
from greyfit.solvers.discovery import discover
from greyfit.solvers.fit import fit_model
from greyfit.solvers.model.compiler import compile_model
from greyfit.solvers.screening.families.lags import ExtraPole, InputLag, SensorLag
from tests.lag_systems import SYSTEMS, TRUTH, declared, lag_record


def screened(result) -> list[str]:
    return [c["effect"] for w in result.warnings if w.code == "missing_effect_likely" for c in w.detail["candidates"]]


def test_each_rewrite_adds_one_state_whose_lag_vanishes_as_tau_goes_to_zero():
    """The rewritten model's right-hand side at w = source equals the declared one, and dw/dt = (s − w)/τ."""
    model = Model.model_validate(declared("thermal"))
    x, u = np.array([1.5, 0.7]), np.array([2.0])
    p = np.array([TRUTH["thermal"][n] for n in ("g1", "b", "g12", "g2")])
    f0 = np.array(compile_model(model).rhs(x, u, p, 0.0)).ravel()
    for new, source in ((SensorLag().rewrite(model, output="T2", dt=0.1)[0], x[1]),
                        (InputLag().rewrite(model, input="P", dt=0.1)[0], u[0]),
                        (ExtraPole().rewrite(model, equation="T2", source="T1", dt=0.1)[0], x[0])):
        cm = compile_model(new)
        assert cm.nx == 3 and new.parameters[-1].value == pytest.approx(0.1)
        tau = 0.25
        pn = np.append(p, tau)
        at_source = np.array(cm.rhs(np.append(x, source), u, pn, 0.0)).ravel()
        np.testing.assert_allclose(at_source[:2], f0, rtol=1e-12)
        assert at_source[2] == pytest.approx(0.0, abs=1e-12)
        off = np.array(cm.rhs(np.append(x, source - 1.0), u, pn, 0.0)).ravel()
        assert off[2] == pytest.approx(1.0 / tau)
    assert SensorLag().rewrite(model, output="T2", dt=0.1)[0].outputs == {"T1": "T1", "T2": "T2_sensed"}


@pytest.mark.parametrize("system", list(SYSTEMS))
def test_right_models_are_not_flagged(system):
    r = fit_model(FitRequest.model_validate({"model": declared(system),
                                             "experiments": [lag_record(system, "none", 0, 3)]}))
    assert r.quality == "good" and "missing_effect_likely" not in {w.code for w in r.warnings}
    for name, value in TRUTH[system].items():
        assert r.parameters[name].value == pytest.approx(value, rel=0.03)


@pytest.mark.parametrize("system,lag", [("rl", "sensor"), ("msd", "input"), ("thermal", "pole")])
def test_a_two_sample_lag_is_named_by_the_lack_of_fit_screen(system, lag):
    r = fit_model(FitRequest.model_validate({"model": declared(system),
                                             "experiments": [lag_record(system, lag, 2.0, 4)]}))
    assert r.quality != "good"
    assert {"sensor_lag", "input_lag", "extra_pole"} & set(screened(r)), screened(r)


@pytest.mark.slow
def test_discovery_adds_the_extra_pole_and_estimates_its_time_constant():
    """Two measured nodes tell a lag between them from one on a sensor or the input: τ = 3 samples = 0.3 s."""
    body = {"model": declared("thermal"), "experiments": [lag_record("thermal", "pole", 3.0, 0)],
            "discovery": {"max_terms": 1}}
    res = discover(DiscoverRequest.model_validate(body))
    assert [s.effect for s in res.steps] == ["extra_pole"], res.conclusion
    assert res.fit.parameters["T1_to_T2_tau"].value == pytest.approx(0.3, rel=0.1)
    for p, value in TRUTH["thermal"].items():
        assert res.fit.parameters[p].value == pytest.approx(value, rel=0.03)
