"""Discrete-time models: ARX template, equation error (one-step predictor), output error, RLS."""
import numpy as np
import pytest
from scipy import signal

from greyfit.schemas import FitRequest
from greyfit.solvers.errors import DataError
from greyfit.solvers.fit import fit_model
from tests.online_systems import SECOND_ORDER, rl_experiment, rl_model, simulate_rl

T = 1e-3


def arx_data(noise=0.0, seed=0, n=3000):
    num, den, _ = signal.cont2discrete(SECOND_ORDER, T, method="zoh")
    t = np.arange(n) * T
    rng = np.random.default_rng(seed)
    u = np.repeat(rng.standard_normal(n // 10 + 1), 10)[:n]     # random steps: rich excitation
    y = signal.lfilter(np.ravel(num), den, u)
    return t, u, y + noise * rng.standard_normal(n), np.ravel(num), den


def arx_request(t, u, y, method, **options):
    return FitRequest.model_validate({
        "model": {"name": "arx221", "inputs": ["u"], "template": {"kind": "arx", "na": 2, "nb": 2, "nk": 1},
                  "discrete": {"Ts": T}},
        "experiments": [{"name": "e", "time": t.tolist(), "inputs": {"u": u.tolist()},
                         "outputs": {"y": y.tolist()}}],
        "method": method, "options": options})


def test_arx_template_by_prediction_error_and_by_rls_is_exact_on_noise_free_data():
    t, u, y, num, den = arx_data()
    truth = {"a1": den[1], "a2": den[2], "b1": num[1], "b2": num[2]}
    batch = fit_model(arx_request(t, u, y, "equation_error"))
    assert batch.success and batch.solver.linear_in_parameters
    rls = fit_model(arx_request(t, u, y, "recursive_least_squares",
                                rls={"gain_law": "decreasing_gain", "initial_covariance": 1e8}))
    for name, value in truth.items():
        assert batch.parameters[name].value == pytest.approx(value, rel=1e-6, abs=1e-12), name
        assert rls.parameters[name].value == pytest.approx(value, rel=1e-3), name


def test_discrete_output_error_refines_the_biased_arx_estimate():
    """ARX by prediction error is biased by output noise (seed 003/004); output error by shooting,
    with the difference equation as the step and started from the ARX estimate, is not."""
    t, u, y, num, den = arx_data(noise=0.01, n=1500)
    arx = fit_model(arx_request(t, u, y, "equation_error"))
    req = arx_request(t, u, y, "single_shooting")
    req.model.parameters = [p.model_copy(update={"value": arx.parameters[p.name].value}) for p in req.model.parameters]
    oe = fit_model(req)
    # converged; "suspect" only because the initial values of the ARX delay states y_1, u_1 are not
    # separately identifiable (a null direction in x0, not in the parameters)
    assert oe.solver.return_status == "Solve_Succeeded" and oe.quality != "failed"
    true_gain = (num[1] + num[2]) / (1 + den[1] + den[2])

    def gain(res):
        p = {k: v.value for k, v in res.parameters.items()}
        return (p["b1"] + p["b2"]) / (1 + p["a1"] + p["a2"])
    assert abs(gain(oe) / true_gain - 1) < 0.01
    assert abs(gain(oe) / true_gain - 1) < 0.5 * abs(gain(arx) / true_gain - 1)
    assert oe.metrics.rmse["y"] < 0.0105   # the noise level: the output is reproduced


def test_rl_circuit_multiple_shooting_in_physical_parameters():
    t, u, i = simulate_rl(2.0, noise=1e-3)
    res = fit_model(FitRequest.model_validate({"model": rl_model(), "experiments": [rl_experiment(t, u, i)],
                                               "method": "multiple_shooting"}))
    assert res.success
    assert res.parameters["R"].value == pytest.approx(2.0, rel=0.01)
    assert res.parameters["L"].value == pytest.approx(0.5, rel=0.01)


def test_sampling_must_match_the_model_sample_time():
    t, u, i = simulate_rl(0.2)
    exp = rl_experiment(t * 2, u, i)
    with pytest.raises(DataError, match="sample_time") as info:
        fit_model(FitRequest.model_validate({"model": rl_model(), "experiments": [exp], "method": "equation_error"}))
    assert info.value.field == "experiments[0].time"
