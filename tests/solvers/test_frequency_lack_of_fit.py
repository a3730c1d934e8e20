"""Frequency fits' lack-of-fit test (solvers/frequency/lack_of_fit.py): a gain or phase trend over
frequency that the model does not explain. Truth computed with numpy/scipy only; the course notes'
PI loop (tests/frequency_systems.py) with a plant pole at 500 rad/s the model lacks (11° of phase at
100 rad/s), and the random systems of tests/frequency_generator.py."""
import json
from pathlib import Path

import numpy as np
import pytest

from greyfit.schemas.frequency import FrequencyFitRequest
from greyfit.solvers.frequency import fit_frequency_response
from greyfit.solvers.frequency.lack_of_fit import trend_test
from tests.frequency_generator import random_case
from tests.frequency_systems import OMEGA, noisy

EXAMPLE = Path(__file__).resolve().parents[2] / "examples" / "frequency_pi_loop_request.json"
TRUTH = {"a1": 20.0, "a2": 500.0, "a3": 2000.0, "b1": 33.2224, "b2": 21.135 ** 2 * 33.2224}


def loop_with_pole(kp: float, ki: float, pole: float) -> np.ndarray:
    """The measured G = P/(1 + PC), the plant P times pole/(s + pole)."""
    s = 1j * OMEGA
    plant = (TRUTH["b1"] * s ** 2 + TRUTH["b2"]) / (s * (s ** 3 + TRUTH["a1"] * s ** 2 + TRUTH["a2"] * s + TRUTH["a3"]))
    plant = plant * pole / (s + pole)
    return plant / (1 + plant * (kp + ki / s))


def fit_loop(seed: int, pole: float):
    body = json.loads(EXAMPLE.read_text())
    body["data"] = []
    for k, (kp, ki, name) in enumerate(((1.0, 1.0, "pi"), (1.65, 0.0, "p_only"))):
        g = noisy(loop_with_pole(kp, ki, pole), 0.02, seed + 100 * k)
        body["data"].append({"name": name, "omega": OMEGA.tolist(), "real": g.real.tolist(),
                             "imag": g.imag.tolist(), "constants": {"Kp": kp, "Ki": ki}})
    return fit_frequency_response(FrequencyFitRequest.model_validate(body))


def test_the_loop_missing_a_pole_at_500_rad_s_is_not_good_and_says_why():
    res = fit_loop(0, 500.0)
    assert res.quality != "good"
    (w,) = [w for w in res.warnings if w.code == "missing_effect_likely"]
    assert w.detail["p_value"] < 1e-6 and "frequency" in w.message
    # the same loop without the extra pole (a pole at 1e9 rad/s) is good
    assert fit_loop(0, 1e9).quality == "good"


@pytest.mark.parametrize("seed", [0, 1])
def test_random_right_models_are_good_and_missing_poles_are_not(seed):
    right = fit_frequency_response(FrequencyFitRequest.model_validate(random_case(seed, "right").body))
    assert right.quality == "good", [w.message for w in right.warnings]
    wrong = fit_frequency_response(FrequencyFitRequest.model_validate(random_case(seed, "missing_pole").body))
    assert wrong.quality != "good" and "missing_effect_likely" in {w.code for w in wrong.warnings}


def test_the_trend_test_is_an_f_test_on_noise_and_finds_a_trend():
    """On pure noise (the parameters' columns random) its p-values are uniform; a linear trend of a
    third of the noise's size over 400 rows is found."""
    rng = np.random.default_rng(1)
    n = 400
    x = np.linspace(-1, 1, n)
    cols = np.column_stack([np.ones(n), x, x ** 2])
    pvals = []
    for _ in range(300):
        jac = rng.standard_normal((n, 3))
        out = trend_test(rng.standard_normal(n), jac, cols)
        assert out is not None
        pvals.append(out[0])
    assert 0.02 < np.mean(np.array(pvals) < 0.05) < 0.09
    out = trend_test(rng.standard_normal(n) + 0.5 * x, rng.standard_normal((n, 3)), cols)
    assert out is not None and out[0] < 1e-3
