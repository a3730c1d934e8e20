"""Excitation checks before the fit (seeds 002 and 003): warnings name inputs and parameters."""
import numpy as np
import pytest
from scipy.integrate import solve_ivp

from greyfit.schemas import FitRequest
from greyfit.solvers.checks.excitation import persistent_excitation_order
from greyfit.solvers.errors import DataError
from greyfit.solvers.fit import fit_model
from tests.systems import MOTOR_A, MOTOR_B, motor_model

T = np.arange(0, 5, 0.005)


def test_persistent_excitation_order_of_standard_signals():
    assert persistent_excitation_order(np.ones(1000)) == 1
    assert persistent_excitation_order(np.sin(2 * np.pi * T / 5)) == 2
    assert persistent_excitation_order(np.sin(2 * np.pi * T / 5) + np.sin(2 * np.pi * 3.1 * T / 5)) == 4
    assert persistent_excitation_order(np.random.default_rng(0).standard_normal(1000)) == 8


def test_motor_driven_by_three_steps_names_the_input_gains():
    """Seed 002: one step on every input; the B entries are flagged, by name."""
    def steps(t):
        return np.full((3, np.size(t)), 1.0) * np.clip((np.atleast_1d(t) - 0.5) / 0.005, 0, 1)
    sol = solve_ivp(lambda t, x: MOTOR_A @ x + MOTOR_B @ steps(t)[:, 0], (0, T[-1]), np.zeros(3),
                    t_eval=T, method="DOP853", rtol=1e-10, atol=1e-12, max_step=0.0025)
    rng = np.random.default_rng(3)
    u = steps(T)
    exp = {"time": T.tolist(), "inputs": {f"u{i + 1}": u[i].tolist() for i in range(3)},
           "outputs": {f"x{i + 1}": (sol.y[i] + 0.01 * rng.standard_normal(T.size)).tolist()
                       for i in range(3)},
           "initial_state": {"x1": 0.0, "x2": 0.0, "x3": 0.0}}
    r = fit_model(FitRequest.model_validate(
        {"model": motor_model(), "experiments": [exp], "method": "single_shooting"}))
    flagged = {w.detail["input"]: w.detail["parameters"] for w in r.warnings if w.code == "input_not_exciting"}
    assert flagged == {"u1": ["b11"], "u2": ["b22"], "u3": ["b33"]}


def rl_request(start_at_rest=False):
    """Seed 003: L di/dt = -R i + v at a constant v (R = 2, L = 0.05), measured at steady state."""
    t = np.arange(0, 1, 0.001)
    i = np.full(t.size, 0.5) + 0.001 * np.random.default_rng(0).standard_normal(t.size)
    return {"model": {"states": ["i"], "inputs": ["v"],
                      "parameters": [{"name": "R", "value": 1.0, "lower": 0},
                                     {"name": "L", "value": 0.1, "lower": 0}],
                      "equations": {"i": "(-R*i + v)/L"}},
            "experiments": [{"time": t.tolist(), "inputs": {"v": [1.0] * t.size},
                             "outputs": {"i": i.tolist()}}],
            "method": "multiple_shooting"}


def test_rl_circuit_at_dc_is_flagged_not_good():
    r = fit_model(FitRequest.model_validate(rl_request()))
    assert r.success is False and r.quality == "suspect"
    codes = {w.code: w for w in r.warnings}
    assert codes["input_not_exciting"].detail["parameters"] == ["L"]
    named = " ".join(w.message for w in r.warnings if w.code in ("hessian_singular", "flat_cost"))
    assert "L" in named and "R" in named


def test_nothing_identifiable_is_a_data_error():
    body = rl_request()
    body["model"]["outputs"] = {"y": "v"}     # the output does not depend on the model at all
    body["experiments"][0]["outputs"] = {"y": [1.0] * 1000}
    with pytest.raises(DataError, match="nothing is identifiable"):
        fit_model(FitRequest.model_validate(body))
