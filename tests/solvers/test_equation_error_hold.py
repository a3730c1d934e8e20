"""Equation error honours `input_interpolation` (issue #8): x' = -a x + b u, a = 100, b = 200,
sampled at 1 ms, only x measured, inputs that change at (almost) every sample."""
import numpy as np
import pytest
from scipy.integrate import solve_ivp

from greyfit.schemas.fit import FitRequest
from greyfit.solvers.fit import fit_model

A, B, TS, N = 100.0, 200.0, 1e-3, 1001


def random_steps(seed: int, hold: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.repeat(rng.uniform(-1.0, 1.0, N // hold + 1), hold)[:N]


def held_record(u: np.ndarray) -> np.ndarray:
    """Exact discretisation for an input held over each sample interval (a digital controller)."""
    ad = np.exp(-A * TS)
    x = np.zeros(N)
    for k in range(N - 1):
        x[k + 1] = ad * x[k] + (1 - ad) * B / A * u[k]
    return x


def linear_record(u: np.ndarray) -> np.ndarray:
    """Exact discretisation for an input linear between samples (first-order hold)."""
    ad = np.exp(-A * TS)
    ramp = 1 - (1 - ad) / (A * TS)
    x = np.zeros(N)
    for k in range(N - 1):
        x[k + 1] = ad * x[k] + B / A * ((1 - ad) * u[k] + ramp * (u[k + 1] - u[k]))
    return x


def test_linear_record_matches_scipy():
    u = random_steps(6, 7)
    t = np.arange(N) * TS
    sol = solve_ivp(lambda tt, x: -A * x + B * np.interp(tt, t, u), (0, t[-1]), [0.0], t_eval=t,
                    rtol=1e-10, atol=1e-12, max_step=TS / 2)
    assert np.max(np.abs(sol.y[0] - linear_record(u))) < 1e-6 * np.max(np.abs(sol.y[0]))


def fit(x: np.ndarray, u: np.ndarray, interpolation: str):
    t = np.arange(N) * TS
    body = {"model": {"states": ["x"], "inputs": ["u"],
                      "parameters": [{"name": "a", "value": 50.0}, {"name": "b", "value": 50.0}],
                      "equations": {"x": "-a*x + b*u"}, "outputs": {"y": "x"}},
            "method": "equation_error", "options": {"input_interpolation": interpolation},
            "experiments": [{"time": t.tolist(), "inputs": {"u": u.tolist()}, "outputs": {"y": x.tolist()}}]}
    return fit_model(FitRequest.model_validate(body))


@pytest.mark.parametrize("seed,hold", [(0, 1), (1, 3), (2, 20)])
def test_zoh_input_recovers_the_pole_within_half_a_percent(seed, hold):
    u = random_steps(seed, hold)
    r = fit(held_record(u), u, "zoh")
    assert r.parameters["a"].value == pytest.approx(A, rel=0.005)
    assert r.parameters["b"].value == pytest.approx(B, rel=0.005)
    assert "held (zoh)" in r.solver.derivative_filter


@pytest.mark.parametrize("seed,hold", [(3, 1), (4, 20)])
def test_foh_input_still_recovers_the_pole(seed, hold):
    u = random_steps(seed, hold)
    r = fit(linear_record(u), u, "foh")
    assert r.parameters["a"].value == pytest.approx(A, rel=0.005)
    assert r.parameters["b"].value == pytest.approx(B, rel=0.005)


def test_held_data_read_as_linear_is_biased():
    """The option matters: the same held record read as foh misplaces the pole (so the zoh result
    above is the option at work, not an estimator insensitive to it)."""
    u = random_steps(5, 1)
    x = held_record(u)
    zoh, foh = fit(x, u, "zoh"), fit(x, u, "foh")
    assert abs(zoh.parameters["a"].value / A - 1) < 0.005
    assert abs(foh.parameters["a"].value / A - 1) > 0.02
