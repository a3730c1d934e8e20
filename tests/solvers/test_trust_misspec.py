"""Misspecification tests that need not name the effect (issue 38), on generated systems with known
truth (tests/generators/misspec.py). One or two seeds per mechanism; the rates over ≥ 20 seeds a row
are in bench/bench_trust.py and docs/trust.md."""
from __future__ import annotations

import numpy as np

from greyfit.schemas.fit import FitRequest
from greyfit.solvers.fit import fit_model
from tests.generators.misspec import make_case


def fit(body: dict):
    return fit_model(FitRequest.model_validate(body))


def codes(result) -> set[str]:
    return {w.code for w in result.warnings}


def covered(result, truth: dict) -> float:
    return float(np.mean([result.parameters[k].ci95[0] <= v <= result.parameters[k].ci95[1] for k, v in truth.items()]))


def test_an_input_held_every_sample_or_two_and_read_as_a_curve_fails_the_independence_test():
    """Pharmacokinetics, an infusion re-set every 1-2 samples and read at `auto` as a smooth curve: the
    intervals miss every true parameter, and the residual depends on the input."""
    case = make_case("held_read_smooth", 2)
    r = fit(case.declared)
    assert case.block == "pk_two_compartment" and covered(r, case.truth) == 0.0
    assert "residual_correlated_with_input" in codes(r) and r.quality == "suspect"
    (w,) = [w for w in r.warnings if w.code == "residual_correlated_with_input"]
    assert w.detail["p_value"] < 1e-6 and w.detail["input"] == "u"


def test_a_right_model_passes_the_independence_test_and_is_good():
    case = make_case("right", 0, "white", "held")
    r = fit(case.declared)
    assert r.quality == "good" and "residual_correlated_with_input" not in codes(r)
    assert covered(r, case.truth) == 1.0


def test_coloured_noise_on_a_right_model_is_said_and_stays_good():
    """A pendulum under AR(1) 0.8 noise: the HAC intervals are several times the white ones; the result
    says it cannot tell coloured noise from a model error, the noise-model test does not reject, and
    the intervals hold the truth."""
    case = make_case("right", 1, "ar1")
    r = fit(case.declared)
    (w,) = [w for w in r.warnings if w.code == "residual_coloured"]
    assert w.detail["widening"] >= 2.0 and "cannot be told" in w.message
    assert r.quality == "good" and covered(r, case.truth) == 1.0


def test_equation_error_gets_no_interpolation_warning():
    """An input that changes every sample, `foh` forced: a warning about output error's interpolation
    (`input_faster_than_sampling`) does not belong to equation error, which reads inputs at the samples."""
    rng = np.random.default_rng(4)
    t = np.arange(400) * 0.1
    u = rng.uniform(-1, 1, t.size)
    x = np.zeros(t.size)
    for k in range(t.size - 1):   # exact discretisation of x' = -x + 2u with the input held
        x[k + 1] = np.exp(-0.1) * x[k] + 2 * (1 - np.exp(-0.1)) * u[k]
    body = {"model": {"states": ["x"], "inputs": ["u"], "equations": {"x": "-a*x + b*u"}, "outputs": {"x": "x"},
                      "parameters": [{"name": "a", "value": 0.8}, {"name": "b", "value": 1.5}]},
            "experiments": [{"time": t.tolist(), "inputs": {"u": u.tolist()}, "outputs": {"x": x.tolist()},
                             "initial_state": {"x": 0.0}}],
            "method": "equation_error", "options": {"input_interpolation": "foh"}}
    assert "input_faster_than_sampling" not in codes(fit(body))
    body["method"] = "single_shooting"   # where it belongs, it still fires
    assert "input_faster_than_sampling" in codes(fit(body))


def test_the_lack_of_fit_screen_holds_its_level_under_coloured_noise():
    """A right DC motor model under AR(1) 0.8 noise: the screen's effective-size score test found a
    "missing effect" here; confirmed under an AR noise model it does not, and the fit is good."""
    case = make_case("right", 8, "ar1", "held")
    r = fit(case.declared)
    assert case.block == "dc_motor"
    assert "missing_effect_likely" not in codes(r) and r.quality == "good"


def test_a_missing_effect_under_a_coloured_residual_is_still_found():
    """Saturable elimination (Michaelis-Menten) in a two-compartment model: the residual is coloured by
    the misfit, and the whitened confirmation keeps the screen's finding."""
    case = make_case("saturable", 1)
    r = fit(case.declared)
    assert case.block == "pk_two_compartment" and "missing_effect_likely" in codes(r) and r.quality == "suspect"


def test_a_small_quadratic_loss_is_found_when_the_validation_record_is_screened_too():
    """A DC motor with a small unmodelled quadratic loss on the shaft (the `quadratic` scenario): the
    declared model absorbs it on the fitted record; screened with the validation record, which drives
    the shaft through other speeds, the score test names the missing ω|ω| term."""
    case = make_case("quadratic", 13)
    r = fit(case.declared)
    assert case.block == "dc_motor" and "d" in case.extra
    (w,) = [w for w in r.warnings if w.code == "missing_effect_likely"]
    assert w.detail["records"] == 2 and "validation record" in w.message
    assert w.detail["candidates"][0]["effect"] == "quadratic_drag" and w.detail["candidates"][0]["p_value"] < 1e-5
    assert r.quality == "suspect"


def test_a_right_model_of_a_held_out_block_is_good_with_the_validation_record_screened():
    """An RC ladder (a block no check was developed on), the right model: the screen reads both records
    and finds nothing, and the intervals hold the truth."""
    case = make_case("right_heldout", 0)
    r = fit(case.declared)
    assert case.block == "rc_ladder"
    assert "missing_effect_likely" not in codes(r) and r.quality == "good" and covered(r, case.truth) == 1.0


def test_a_loss_no_screened_effect_names_is_found_on_a_held_out_block():
    """The RC ladder with a leak growing as v2^1.5 (no screened law is that power): the screen's nearest
    law (a quadratic one) explains enough of the residual, and the fit is not `good`."""
    case = make_case("power_loss", 3)
    r = fit(case.declared)
    assert case.block == "rc_ladder" and case.extra == ["g15"]
    assert "missing_effect_likely" in codes(r) and r.quality == "suspect"
