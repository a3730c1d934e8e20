"""Time-varying parameters in batch fits: seed 000's k4 steps and a drifting resistance."""
import numpy as np
import pytest

from greyfit.schemas import FitRequest
from greyfit.solvers.fit import fit_model
from tests.online_systems import rl_experiment, rl_model, simulate_rl
from tests.systems import SEAT_TRUTH, seat_experiment, seat_k4_step, seat_model, simulate_seat


@pytest.mark.slow
def test_seat_k4_steps_come_out_as_steps():
    """Seed 000 Case 1 (noise-free states and derivatives, as in the paper): k4 switches
    0.9e5 -> 1.8e5 -> 0.9e5 -> 1.8e5 N/m at 0.25/0.5/0.75 s. 333 segments of 3 ms, not aligned
    with the switches."""
    t, x, dx, w, wd = simulate_seat(seed=0, k4_of_t=seat_k4_step)
    model = seat_model({k: 1.2 * v for k, v in SEAT_TRUTH.items()})
    for p in model["parameters"]:
        if p["name"] == "k4":
            p["time_varying"] = {"kind": "piecewise_constant", "segments": 333, "weight": 1e-5}
    res = fit_model(FitRequest.model_validate({"model": model, "method": "equation_error",
                                               "experiments": [seat_experiment(t, x, w, wd, dx)]}))
    assert res.success and res.solver.return_status == "IRLS_Converged"
    for name, truth in SEAT_TRUTH.items():
        if name != "k4":
            assert res.parameters[name].value == pytest.approx(truth, rel=0.005), name
    times = np.array(res.trajectory.time)
    k4 = np.array(res.trajectory.values["k4"])
    for (a, b), level in zip(((0, .25), (.25, .5), (.5, .75), (.75, 1)), (0.9e5, 1.8e5, 0.9e5, 1.8e5)):
        inside = (times > a + 0.01) & (times < b - 0.01)
        assert np.max(np.abs(k4[inside] / level - 1)) < 0.02, (a, b)
    crossings = times[1:][np.diff(np.sign(k4 - 1.35e5)) != 0]
    assert crossings.size == 3
    assert np.max(np.abs(crossings - np.array([0.25, 0.5, 0.75]))) <= 0.010
    assert "k4__0" in res.parameters and len(res.trajectory.lower["k4"]) == times.size


def test_drifting_resistance_rate_from_a_piecewise_linear_batch_fit():
    """R from 2 to 3 Ω over 10 s; seed 003's discrete RL model (nonlinear in R, L: Ipopt with the
    smooth total-variation rows), R piecewise linear on 11 knots."""
    t, u, i = simulate_rl(10.0, r_of_t=lambda tt: 2.0 + 0.1 * tt, noise=1e-3)
    model = rl_model(R=2.5, L=0.6)
    model["parameters"][0]["time_varying"] = {"kind": "piecewise_linear", "segments": 10, "weight": 1e-4}
    res = fit_model(FitRequest.model_validate({"model": model, "experiments": [rl_experiment(t, u, i)],
                                               "method": "equation_error"}))
    assert res.success
    times = np.array(res.trajectory.time)
    r_hat = np.array(res.trajectory.values["R"])
    assert np.polyfit(times, r_hat, 1)[0] == pytest.approx(0.1, rel=0.02)
    assert np.max(np.abs(r_hat / (2.0 + 0.1 * times) - 1)) < 0.01
    assert res.parameters["L"].value == pytest.approx(0.5, rel=0.01)


def test_time_varying_is_refused_by_online_methods_and_constraints():
    t, u, i = simulate_rl(0.5)
    model = rl_model()
    model["parameters"][0]["time_varying"] = {"kind": "piecewise_constant", "segments": 2}
    from greyfit.solvers.errors import DataError, ModelDefinitionError
    with pytest.raises(DataError, match="time_varying"):
        fit_model(FitRequest.model_validate({"model": model, "experiments": [rl_experiment(t, u, i)],
                                             "method": "recursive_least_squares"}))
    model["constraints"] = ["R >= 0.1"]
    with pytest.raises(ModelDefinitionError, match="constraints on a time-varying"):
        fit_model(FitRequest.model_validate({"model": model, "experiments": [rl_experiment(t, u, i)],
                                             "method": "equation_error"}))
