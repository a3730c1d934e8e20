"""Validation records of a fit and fits with every parameter fixed, against scipy simulations."""
import numpy as np
from scipy.integrate import solve_ivp

from greyfit.schemas import FitRequest
from greyfit.solvers.fit import fit_model

DUFFING_TRUTH = {"c": 0.3, "k": 2.0, "k3": 1.5}
NOISE = 0.01


def duffing_input(t, phase=0.0):
    return 0.8 * np.sin(1.1 * t + phase) + 0.5 * np.sin(2.7 * t)


def simulate_duffing(t, params, x0, u):
    """scipy on the linearly interpolated input samples (what foh means)."""
    def rhs(tt, s):
        x, v = s
        return [v, np.interp(tt, t, u) - params["c"] * v - params["k"] * x - params["k3"] * x ** 3]
    return solve_ivp(rhs, (t[0], t[-1]), list(x0), t_eval=t, method="DOP853", rtol=1e-11, atol=1e-13,
                     max_step=(t[1] - t[0]) / 2).y


def duffing_model(fixed=False):
    guess = DUFFING_TRUTH if fixed else {"c": 0.5, "k": 1.5, "k3": 1.0}
    return {"name": "duffing", "states": ["x", "v"], "inputs": ["u"],
            "parameters": [{"name": n, "value": v, "lower": 0.0, "fixed": fixed} for n, v in guess.items()],
            "equations": {"x": "v", "v": "u - c*v - k*x - k3*x^3"}, "outputs": {"x": "x"}}


def record(name, t, x, u, seed):
    rng = np.random.default_rng(seed)
    return {"name": name, "time": t.tolist(), "inputs": {"u": u.tolist()},
            "outputs": {"x": (x[0] + NOISE * rng.standard_normal(t.size)).tolist()}}


def metrics(measured, simulated):
    r = simulated - measured
    nrmse = np.linalg.norm(r) / np.linalg.norm(measured - measured.mean())
    return np.sqrt(np.mean(r ** 2)), 100 * (1 - nrmse), nrmse


def test_validation_metrics_match_an_independent_simulation():
    t = np.linspace(0, 30, 601)
    u = duffing_input(t)
    x = simulate_duffing(t, DUFFING_TRUTH, (0.5, 0.0), u)
    est = record("est", t[:301], x[:, :301], u[:301], 1)
    cont = record("cont", t[300:], x[:, 300:], u[300:], 2)      # starts at est's last sample
    t2 = np.linspace(0, 15, 301)
    u2 = duffing_input(t2, phase=1.0)
    x2 = simulate_duffing(t2, DUFFING_TRUTH, (-0.4, 0.3), u2)
    other = record("other", t2, x2, u2, 3)                       # a separate run, state unknown
    req = FitRequest.model_validate({"model": duffing_model(), "experiments": [est],
                                     "validation": [cont, other], "options": {"substeps": 4}})
    res = fit_model(req)
    assert res.success
    theta = {k: v.value for k, v in res.parameters.items()}
    for k, v in DUFFING_TRUTH.items():
        assert abs(theta[k] - v) < 4 * res.parameters[k].stderr, (k, theta[k])
    val = {e.name: e for e in res.validation.experiments}
    assert val["cont"].initial_state_source == "contiguous"
    assert val["other"].initial_state_source == "estimated" and val["other"].estimated_states == ["x", "v"]

    # independent: scipy with the fitted parameters from the fitted initial state across both records
    x0 = res.initial_states["est"]
    whole = simulate_duffing(t, theta, (x0["x"], x0["v"]), u)
    rmse, fitp, nrmse = metrics(np.array(cont["outputs"]["x"]), whole[0, 300:])
    assert abs(val["cont"].rmse["x"] - rmse) < 1e-4 * rmse
    assert abs(val["cont"].fit_percent["x"] - fitp) < 1e-4 and abs(val["cont"].nrmse["x"] - nrmse) < 1e-6
    # the separate run from its reported (estimated) initial state
    s0 = val["other"].initial_state
    sim2 = simulate_duffing(t2, theta, (s0["x"], s0["v"]), u2)
    rmse2, fitp2, _ = metrics(np.array(other["outputs"]["x"]), sim2[0])
    assert abs(val["other"].rmse["x"] - rmse2) < 1e-4 * rmse2 and abs(val["other"].fit_percent["x"] - fitp2) < 1e-4
    assert abs(s0["x"] + 0.4) < 0.02 and abs(s0["v"] - 0.3) < 0.05
    # pooled over both records, and a good model validates at the noise level
    both = np.concatenate([np.array(cont["outputs"]["x"]), np.array(other["outputs"]["x"])])
    rmse_all, fit_all, _ = metrics(both, np.concatenate([whole[0, 300:], sim2[0]]))
    assert abs(res.validation.rmse["x"] - rmse_all) < 1e-4 * rmse_all
    assert abs(res.validation.fit_percent["x"] - fit_all) < 1e-4
    assert 0.8 * NOISE < res.validation.rmse["x"] < 1.3 * NOISE


def test_a_request_with_every_parameter_fixed_is_a_simulation():
    t = np.linspace(0, 15, 301)
    u = duffing_input(t)
    x = simulate_duffing(t, DUFFING_TRUTH, (0.5, 0.0), u)
    exp = record("e", t, x, u, 4)
    exp["initial_state"] = {"x": 0.5, "v": 0.0}
    res = fit_model(FitRequest.model_validate({"model": duffing_model(fixed=True), "experiments": [exp],
                                               "options": {"substeps": 4, "return_traces": True}}))
    assert res.success and res.covariance is None and "simulated, not fitted" in res.message
    assert res.solver.return_status == "Simulation" and res.metrics.nvarys == 0
    rmse, fitp, _ = metrics(np.array(exp["outputs"]["x"]), x[0])
    assert abs(res.metrics.rmse["x"] - rmse) < 1e-4 * rmse and abs(res.metrics.fit_percent["x"] - fitp) < 1e-4
    assert np.max(np.abs(np.array(res.traces[0].simulated["x"]) - x[0])) < 1e-5
    assert all(p.fixed for p in res.parameters.values())
