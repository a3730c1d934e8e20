"""Simulation with given parameters: against the fit's own traces, against scipy, initial states, k-step."""
import numpy as np
from scipy.integrate import solve_ivp

from greyfit.schemas import Experiment, FitOptions, FitRequest, Model
from greyfit.solvers.fit import fit_model
from greyfit.solvers.simulation.simulate import simulate_experiments, validation_metrics
from tests.systems import (
    SEAT_TRUTH,
    msd_experiment,
    msd_input,
    msd_model,
    seat_model,
    seat_rhs,
    simulate_msd,
    simulate_seat,
)


def _msd_fit(method: str):
    t = np.linspace(0, 10, 201)
    req = FitRequest.model_validate({
        "model": msd_model(), "method": method, "options": {"return_traces": True, "substeps": 2},
        "experiments": [msd_experiment(t, simulate_msd(t), noise=0.01, seed=3)]})
    return req, fit_model(req)


def test_simulating_the_fitted_model_reproduces_the_fits_own_outputs():
    for method in ("single_shooting", "multiple_shooting"):
        req, res = _msd_fit(method)
        params = {k: v.value for k, v in res.parameters.items()}
        sim = simulate_experiments(req.model, params, req.experiments, req.options, res.initial_states)[0]
        assert sim.initial_state_source == "provided"
        for out, fitted in res.traces[0].simulated.items():
            a, b = np.array(sim.outputs[out]), np.array(fitted)
            assert np.max(np.abs(a - b)) <= 1e-9 * np.max(np.abs(b)), (method, out)


def _seat_against_scipy(n=1000):
    """The seat model (seed 000) from rest with the true parameters; scipy integrates the same
    linearly interpolated input (what foh means), so the difference is the integrator's alone."""
    t, x_exact, _, w, wd = simulate_seat(seed=0, n=n)

    def rhs(tt, s):
        wi, wdi = np.interp(tt, t, w), np.interp(tt, t, wd)
        return seat_rhs(tt, s, SEAT_TRUTH, lambda _: wi, lambda _: wdi)

    ref = solve_ivp(rhs, (0, t[-1]), np.zeros(8), t_eval=t, method="DOP853", rtol=1e-11, atol=1e-14,
                    max_step=t[1] / 4).y
    model = Model.model_validate(seat_model())
    exp = Experiment.model_validate({"name": "seat", "time": t.tolist(),
                                     "inputs": {"w": w.tolist(), "wd": wd.tolist()},
                                     "initial_state": {s: 0.0 for s in model.states}})
    return model, exp, ref, x_exact


def test_seat_model_with_true_parameters_matches_scipy_within_the_integrator_tolerance():
    model, exp, ref, x_exact = _seat_against_scipy()
    rms = np.sqrt(np.mean(ref ** 2, axis=1))[:, None]
    # RK4 error falls as h^4: 4 substeps per 1 ms sample give ~7e-6 of each state's RMS, 1 substep ~4e-3
    for opts, tol in ((FitOptions(substeps=4), 2e-5), (FitOptions(integrator="cvodes"), 1e-5),
                      (FitOptions(substeps=1), 1e-2)):
        sim = simulate_experiments(model, SEAT_TRUTH, [exp], opts)[0]
        xs = np.array([sim.states[s] for s in model.states])
        assert sim.initial_state_source == "experiment"
        err = np.max(np.abs(xs - ref) / rms)
        assert err < tol, (opts, err)
    # against the exact band-limited input the linear interpolation between 1 ms samples costs ~1e-3
    assert np.max(np.abs(xs - x_exact) / rms) < 5e-3


def test_initial_state_estimated_on_a_leading_window_recovers_the_truth():
    t = np.linspace(0, 10, 401)
    x = simulate_msd(t, x0=(0.3, -0.2))
    model = Model.model_validate(msd_model())
    exp = Experiment.model_validate(msd_experiment(t, x, outputs=("x",)))   # only position measured
    truth = {"m": 2.0, "c": 0.8, "k": 5.0}
    sim = simulate_experiments(model, truth, [exp], FitOptions(substeps=4), estimate_window=40)[0]
    assert sim.initial_state_source == "estimated" and sim.estimated_states == ["x", "v"]
    assert sim.estimate_window == 40
    # tolerance: the linear interpolation of the sinusoidal input between 25 ms samples (~1e-3 of u)
    assert abs(sim.initial_state["x"] - 0.3) < 1e-4 and abs(sim.initial_state["v"] + 0.2) < 1e-4
    assert np.max(np.abs(np.array(sim.states["v"]) - x[1])) < 1e-3 * np.max(np.abs(x[1]))
    # a state given in the experiment is kept, the other one estimated
    exp.initial_state = {"x": 0.3}
    sim = simulate_experiments(model, truth, [exp], FitOptions(substeps=4))[0]
    assert sim.estimated_states == ["v"] and sim.initial_state["x"] == 0.3
    assert abs(sim.initial_state["v"] + 0.2) < 1e-4


def test_k_step_ahead_prediction_restarts_from_the_measured_states():
    t = np.linspace(0, 10, 201)
    x = simulate_msd(t)
    model = Model.model_validate(msd_model())
    wrong = {"m": 2.0, "c": 0.4, "k": 6.0}   # a poor model: the free simulation drifts away
    exp = Experiment.model_validate(msd_experiment(t, x))
    opts = FitOptions(substeps=4)
    free = validation_metrics(model, wrong, [exp], opts)
    sims = {k: simulate_experiments(model, wrong, [exp], opts, horizon=k)[0] for k in (1, 5, 400)}
    errs = {k: np.sqrt(np.mean((np.array(s.predicted["x"]) - x[0]) ** 2)) for k, s in sims.items()}
    assert errs[1] < errs[5] < free.rmse["x"] * 0.5
    # a horizon beyond the record is the free simulation
    assert np.array_equal(np.array(sims[400].predicted["x"]), np.array(sims[400].outputs["x"]))
    # one step ahead from exact states with the true model: the input interpolation's error only
    # (sample 0 is the free simulation from the estimated initial state)
    exact = simulate_experiments(model, {"m": 2.0, "c": 0.8, "k": 5.0}, [exp], opts, horizon=1)[0]
    assert np.max(np.abs(np.array(exact.predicted["x"][1:]) - x[0, 1:])) < 1e-6
    # an independent one-step prediction for one sample: scipy from the measured state at t[99]
    k = 100
    sol = solve_ivp(lambda tt, s: [s[1], (np.interp(tt, t, msd_input(t)) - 0.4 * s[1] - 6.0 * s[0]) / 2.0],
                    (t[k - 1], t[k]), x[:, k - 1], rtol=1e-11, atol=1e-13)
    assert abs(sims[1].predicted["x"][k] - sol.y[0, -1]) < 1e-7
