"""An ODE model linearised at an operating point as the model of a frequency-response fit.

Truths are worked out by hand in tests/linearised_systems.py (seed 001's plant through scipy).
"""
import numpy as np
import pytest

from greyfit.schemas.frequency import FrequencyFitRequest
from greyfit.solvers.errors import DataError, ModelDefinitionError
from greyfit.solvers.frequency import fit_frequency_response
from greyfit.solvers.frequency.linearise import characteristic_polynomial, transfer_polynomials
from tests.frequency_systems import NAMES, TRUTH, frequency_data, seed001_model
from tests.linearised_systems import (
    PENDULUM_TRUTH,
    TANK_INFLOW,
    TANK_TRUTH,
    pendulum_equilibrium,
    pendulum_model,
    pendulum_response,
    response_data,
    seed001_ode_model,
    tank_model,
    tank_response,
)

GUESS = {n: 1.5 * v for n, v in TRUTH.items()}
PENDULUM_OMEGA = np.logspace(-1, 2, 41)
TANK_OMEGA = np.logspace(-2, 1, 31)


def _fit(model: dict, data: list[dict], **options):
    return fit_frequency_response(FrequencyFitRequest.model_validate(
        {"model": model, "data": data, "options": options}))


def _relative_errors(result, truth: dict) -> dict:
    return {n: result.parameters[n].value / truth[n] - 1 for n in truth}


def test_faddeev_leverrier_gives_the_transfer_function_of_a_random_state_space():
    import casadi as ca
    rng = np.random.default_rng(3)
    a, b, c, d = rng.normal(size=(5, 5)), rng.normal(size=(5, 1)), rng.normal(size=(1, 5)), 0.7
    coef, _ = characteristic_polynomial(ca.SX(a))
    assert np.allclose([float(ca.evalf(x)) for x in coef[::-1]], np.poly(a), rtol=1e-10)
    num, den = transfer_polynomials(ca.SX(a), ca.SX(b), ca.SX(c), ca.SX(d))
    num, den = (np.array([float(ca.evalf(x)) for x in poly]) for poly in (num, den))
    s = 0.3 + 2.0j
    direct = (c @ np.linalg.solve(s * np.eye(5) - a, b))[0, 0] + d
    assert np.polyval(num, s) / np.polyval(den, s) == pytest.approx(direct, rel=1e-10)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_seed001_plant_as_an_ode_in_its_pi_loop_within_two_percent(seed):
    """Seed 001's plant written as a 4-state ODE, measured as P/(1+PC) with (Kp, Ki) = (1, 1), 41
    frequencies, 2 % noise: the linearised route gives the transfer-function route's fit."""
    data = [frequency_data(TRUTH, 1, 1, seed=seed, name="pi")]
    ode = _fit(seed001_ode_model(GUESS), data)
    assert ode.success and ode.frequency_response.stable
    assert max(abs(e) for e in _relative_errors(ode, TRUTH).values()) < 0.02
    tf = _fit(seed001_model(GUESS), data)
    for n in NAMES:
        assert ode.parameters[n].value == pytest.approx(tf.parameters[n].value, rel=1e-6)
        assert ode.parameters[n].stderr == pytest.approx(tf.parameters[n].stderr, rel=1e-4)
    # the fitted loop is the PI loop around det(sI - A) = s (s³ + a1 s² + a2 s + a3): degree 5
    assert len(ode.frequency_response.data[0].denominator) == 6


def test_seed001_ode_jointly_with_a_second_controller():
    data = [frequency_data(TRUTH, 1, 1, seed=5, name="pi"), frequency_data(TRUTH, 1.65, 0, seed=6, name="p")]
    res = _fit(seed001_ode_model(GUESS), data)
    assert res.success and all(loop.stable for loop in res.frequency_response.loops)
    assert max(abs(e) for e in _relative_errors(res, TRUTH).values()) < 0.02


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_pendulum_linearised_at_the_equilibrium_it_solves_for(seed):
    """m l² θ'' = τ − m g l sin θ − c θ' at τ0 = 1 N m: x*(θ) is solved for each trial θ; the
    equilibrium angle depends on m l, so m, l and c are all identifiable from one response."""
    g = pendulum_response(PENDULUM_TRUTH, PENDULUM_OMEGA)
    res = _fit(pendulum_model({"m": 0.3, "l": 0.8, "c": 0.5}), [response_data(g, PENDULUM_OMEGA, 0.02, seed)])
    assert res.success and res.frequency_response.stable
    for name, err in _relative_errors(res, PENDULUM_TRUTH).items():
        assert abs(err) < 0.02, name
        # within 3 standard errors as well (the noise is what the covariance assumes)
        assert abs(err) * PENDULUM_TRUTH[name] < 3 * res.parameters[name].stderr, name
    point = res.frequency_response.operating_point
    assert point["th"] == pytest.approx(pendulum_equilibrium(PENDULUM_TRUTH), rel=0.01)
    assert point["om"] == pytest.approx(0.0, abs=1e-9) and point["tau"] == 1.0


def test_a_start_without_equilibrium_is_left_for_one_with_it():
    """From m = 0.27 (m g l = 1.06 N m, just above τ0) the search crosses θ where no equilibrium exists;
    those evaluations are NaN for Ipopt, which steps back, and the fit still lands on the truth."""
    g = pendulum_response(PENDULUM_TRUTH, PENDULUM_OMEGA)
    res = _fit(pendulum_model({"m": 0.27, "l": 0.4, "c": 0.2}), [response_data(g, PENDULUM_OMEGA, 0.02, 0)])
    assert res.success
    assert max(abs(e) for e in _relative_errors(res, PENDULUM_TRUTH).values()) < 0.02


@pytest.mark.parametrize("equilibrium", ["given", "solve"])
def test_tank_with_square_root_outflow(equilibrium):
    """A dh/dt = u − k√h at u0 = 0.2: 'given' takes the measured level h0 = 0.16 as the equilibrium
    (k = u0/√h0 by the equality constraint), 'solve' finds h*(θ) = (u0/k)² from a start of 0.1."""
    g = tank_response(TANK_TRUTH, TANK_OMEGA)
    level = 0.16 if equilibrium == "given" else 0.1
    errors = []
    for seed in range(3):
        res = _fit(tank_model({"A": 1.0, "k": 1.0}, level, equilibrium=equilibrium),
                   [response_data(g, TANK_OMEGA, 0.02, seed)])
        assert res.success and res.frequency_response.stable
        errors.append(max(abs(e) for e in _relative_errors(res, TANK_TRUTH).values()))
        assert res.frequency_response.operating_point["h"] == pytest.approx((TANK_INFLOW / 0.5) ** 2, rel=0.02)
    assert max(errors) < 0.02
    if equilibrium == "given":
        assert res.parameters["k"].value == pytest.approx(TANK_INFLOW / 0.4, rel=1e-7)
        assert "equality constraints" in res.covariance_note


def _pendulum(**changes) -> dict:
    model = pendulum_model({"m": 0.8, "l": 0.3, "c": 0.1})
    for key, value in changes.items():
        if key in ("states", "inputs", "equilibrium"):
            model["operating_point"][key] = value
        else:
            model[key] = value
    return model


@pytest.mark.parametrize("changes,error,field,fragment", [
    ({"states": {"th": 0.3, "om": 0.0, "phi": 1.0}}, DataError, "model.operating_point.states.phi",
     "not a model state"),
    ({"states": {"th": 0.3}}, DataError, "model.operating_point.states.om", "no value for state 'om'"),
    ({"inputs": {"tau": 1.0, "v": 0.0}}, DataError, "model.operating_point.inputs.v", "not a model input"),
    ({"states": {"th": 0.3, "om": 0.5}, "equilibrium": "given"}, DataError, "model.operating_point.states",
     "not an equilibrium whatever the parameters: dth/dt = 0.5"),
    ({"inputs": {"tau": 5.0}}, DataError, "model.operating_point", "no equilibrium"),   # τ0 > m g l
    ({"output": "speed"}, DataError, "model.output", "not a model output"),
    ({"outputs": {"angle": "th", "zero": "0*om"}, "output": "zero"}, ModelDefinitionError, "model.output",
     "does not respond"),
    ({"discrete": {"Ts": 0.01}}, ModelDefinitionError, "model.discrete", "discrete-time"),
])
def test_bad_operating_points_name_the_field(changes, error, field, fragment):
    om = np.logspace(-1, 1, 5)
    data = [response_data(pendulum_response(PENDULUM_TRUTH, om), om, 0.0, 0)]
    with pytest.raises(error, match=fragment) as info:
        _fit(_pendulum(**changes), data)
    assert info.value.field == field


def test_two_inputs_need_the_input_named():
    model = _pendulum(inputs={"tau": 1.0, "v": 0.0})
    model["inputs"] = ["tau", "v"]
    om = np.logspace(-1, 1, 5)
    data = [response_data(pendulum_response(PENDULUM_TRUTH, om), om, 0.0, 0)]
    with pytest.raises(DataError, match="name the one the data respond to") as info:
        _fit(model, data)
    assert info.value.field == "model.input"
    model["input"] = "tau"
    assert _fit(model, data).success


def test_data_set_constants_that_move_the_equilibrium_are_refused_with_solve():
    om = np.logspace(-1, 1, 5)
    data = [dict(response_data(pendulum_response(PENDULUM_TRUTH, om), om, 0.0, 0), constants={"g": 5.0})]
    with pytest.raises(ModelDefinitionError, match="own equilibrium") as info:
        _fit(_pendulum(), data)
    assert info.value.field == "model.operating_point.equilibrium"
