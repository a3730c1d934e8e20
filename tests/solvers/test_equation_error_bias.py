"""Equation error says when noise in its regressors biases it (issue 22): the instrumental-variable check.

Truth: the noise-reduction paper's examples (Robust parameter estimation by noise reduction):
20000/(s² + 2s + 10000) and 200/(s + 100) sampled exactly with a zero-order hold at 1 ms, input
sin(2π·2t) + 0.1 sin(2π·20t), white output noise of power 1e-5; the models are their exact sampled
forms in the physical parameters (tests/online_systems.py). Controls: the same first-order case and
a continuous mass-spring-damper (noisy states, Savitzky-Golay derivatives), where the bias is small.
"""
import numpy as np
import pytest

from greyfit.schemas import FitRequest
from greyfit.solvers.fit import fit_model
from tests.online_systems import (
    FIRST_ORDER,
    SECOND_ORDER,
    first_order_model,
    second_order_model,
    seed004_experiment,
    simulate_seed004,
)
from tests.systems import MSD_TRUTH, msd_experiment, msd_model, simulate_msd

SECOND_TRUTH = {"ap1": 2.0, "ap2": 1e4, "bp2": 2e4}


def _fit(model, experiment, **options):
    return fit_model(FitRequest.model_validate({"model": model, "experiments": [experiment],
                                                "method": "equation_error", "options": options}))


@pytest.mark.parametrize("seed", range(5))
def test_raw_equation_error_on_the_second_order_example_is_not_good_and_the_prefiltered_one_is(seed):
    """Before: ap1 off by +1100 % (the damping, 2 s⁻¹ beside ωn² = 1e4) and `good`."""
    t, u, y = simulate_seed004(SECOND_ORDER, seed=seed)
    raw = _fit(second_order_model(), seed004_experiment(t, u, y))
    assert raw.parameters["ap1"].value > 3 * SECOND_TRUTH["ap1"]            # the bias is real
    assert not raw.success and raw.quality == "suspect"
    (w,) = [w for w in raw.warnings if w.code == "errors_in_variables_bias"]
    assert "ap1" in w.detail["parameters"] and "prefilter" in w.message
    iv, ls = w.detail["instrumental"]["ap1"], w.detail["least_squares"]["ap1"]
    assert abs(iv - 2.0) < abs(ls - 2.0) / 3                               # the IV value points at the truth
    filtered = _fit(second_order_model(), seed004_experiment(t, u, y), prefilter={"cutoff_hz": 5.0})
    assert filtered.quality == "good" and not any(w.code == "errors_in_variables_bias" for w in filtered.warnings)
    assert filtered.parameters["ap1"].value == pytest.approx(2.0, rel=0.05)


def test_no_alarm_where_the_bias_is_negligible():
    """First order at the same noise (bias 0.2 %, 5 seeds), and the mass-spring-damper with 2 % state noise
    (10 seeds): the check stays quiet and the fits are good."""
    for seed in range(5):
        t, u, y = simulate_seed004(FIRST_ORDER, seed=seed)
        res = _fit(first_order_model(), seed004_experiment(t, u, y))
        assert res.quality == "good", [w.message for w in res.warnings]
        assert res.parameters["ap"].value == pytest.approx(100.0, rel=0.01)
    t = np.linspace(0, 20, 1001)
    states = simulate_msd(t)
    for seed in range(10):
        res = _fit(msd_model(), msd_experiment(t, states, noise=0.02, seed=seed))
        assert not any(w.code == "errors_in_variables_bias" for w in res.warnings), seed
        assert res.quality == "good" and res.parameters["k"].value == pytest.approx(MSD_TRUTH["k"], rel=0.02)


def test_noise_free_record_gives_no_alarm():
    t, u, y = simulate_seed004(SECOND_ORDER, noise_power=0.0)
    res = _fit(second_order_model(), seed004_experiment(t, u, y))
    assert res.quality == "good" and res.parameters["ap1"].value == pytest.approx(2.0, rel=1e-3)
