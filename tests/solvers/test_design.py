"""Experiment design against simulated truth: the designed input shrinks what it promises, as predicted.

A mass-spring-damper run with one step excites its mass and damping only during the first seconds;
the D-optimal input of the same length and amplitude must shrink their standard errors ≥ 3× in real
fits of simulated records, and the design's predicted standard errors must be what the fits report
and what their spread shows. The rival-model case (T-optimal) separates Coulomb friction from
quadratic damping. Seed sweeps (10+ seeds, the loop naming the truth) live in bench/bench_design.py.
"""
from __future__ import annotations

import numpy as np
import pytest

from greyfit.schemas.design import DesignRequest
from greyfit.schemas.fit import FitRequest
from greyfit.schemas.simulate import SimulateRequest
from greyfit.solvers.design import design_experiment
from greyfit.solvers.errors import DataError, ModelDefinitionError
from greyfit.solvers.fit import fit_model
from greyfit.solvers.simulation.simulate import simulate_request

TRUE = {"m": 1.0, "c": 2.0, "k": 4.0}
MSD = {"name": "msd", "states": ["x", "v"], "inputs": ["u"],
       "parameters": [{"name": n, "value": v, "lower": 0.01, "upper": 100} for n, v in TRUE.items()],
       "equations": {"x": "v", "v": "(u - c*v - k*x)/m"}, "outputs": {"y": "x"}}
SIGMA = 0.01
TS, N = 0.1, 301
STEP = {"name": "step", "time": [round(TS * i, 10) for i in range(N)], "inputs": {"u": [1.0] * N},
        "initial_state": {"x": 0.0, "v": 0.0}}


def _request(**extra) -> DesignRequest:
    body = {"model": MSD, "inputs": {"u": {"lower": -1.0, "upper": 1.0}}, "outputs": {"y": SIGMA},
            "duration": TS * (N - 1), "sample_time": TS, "hold": 0.3, "baseline": STEP,
            "options": {"starts": 1, "max_iterations": 60}}
    body.update(extra)
    return DesignRequest.model_validate(body)


@pytest.fixture(scope="module")
def designed():
    return design_experiment(_request())


def _fits(experiment: dict, seeds: range) -> tuple[np.ndarray, np.ndarray]:
    sim = simulate_request(SimulateRequest.model_validate({"model": MSD, "experiments": [experiment]}))
    y = np.asarray(sim.experiments[0].outputs["y"])
    start = [{**p, "value": p["value"] * 1.3} for p in MSD["parameters"]]
    estimates, stderrs = [], []
    for seed in seeds:
        noisy = y + SIGMA * np.random.default_rng(seed).standard_normal(len(y))
        fit = fit_model(FitRequest.model_validate(
            {"model": {**MSD, "parameters": start}, "experiments": [{**experiment, "outputs": {"y": list(noisy)}}]}))
        assert fit.quality == "good", fit.message
        estimates.append([fit.parameters[n].value for n in TRUE])
        stderrs.append([fit.parameters[n].stderr for n in TRUE])
    return np.asarray(estimates), np.asarray(stderrs)


def test_designed_input_shrinks_the_poorly_excited_parameters_as_predicted(designed):
    exp = designed.experiment.model_dump()
    u = np.asarray(exp["inputs"]["u"])
    assert len(u) == N and np.all(u >= -1 - 1e-9) and np.all(u <= 1 + 1e-9)
    est_d, se_d = _fits(exp, range(12))
    est_s, se_s = _fits(STEP, range(12))
    for i, name in enumerate(TRUE):
        predicted = designed.parameters[name]
        # the prediction is the fit's own Jacobian covariance, before any data are taken
        assert predicted.stderr == pytest.approx(np.median(se_d[:, i]), rel=0.05)
        assert predicted.stderr_baseline == pytest.approx(np.median(se_s[:, i]), rel=0.05)
    # and the estimates' errors over the noise draws: mean z² is 1 when the predicted errors are
    # the spread (36 terms: its sd ~0.24); 0.4-2 fails predictions off by ~1.6x either way
    z = (est_d - np.array(list(TRUE.values()))) / np.array([designed.parameters[n].stderr for n in TRUE])
    assert 0.4 < float(np.mean(z ** 2)) < 2.0
    for name in ("m", "c"):   # the step excites them only in its first seconds
        i = list(TRUE).index(name)
        assert np.std(est_s[:, i], ddof=1) / np.std(est_d[:, i], ddof=1) >= 3.0
        assert designed.parameters[name].stderr_baseline / designed.parameters[name].stderr >= 3.0


def test_design_is_reproducible_and_respects_the_rate_limit():
    request = _request(inputs={"u": {"lower": -1.0, "upper": 1.0, "max_rate": 4.0}},
                       parameters_of_interest=["c"], criterion="A", baseline=None, duration=10.0)
    first, second = design_experiment(request), design_experiment(request)
    assert first.experiment.inputs == second.experiment.inputs
    u = np.asarray(first.experiment.inputs["u"])
    jumps = np.abs(np.diff(u))
    assert np.max(jumps) <= 4.0 * 0.3 + 1e-6   # max_rate × hold between held values
    assert list(first.parameters) == ["c"]


def test_multisine_design_stays_inside_the_amplitude():
    result = design_experiment(_request(signal="multisine", frequencies=[0.05, 0.1, 0.2, 0.4], baseline=None))
    u = np.asarray(result.experiment.inputs["u"])
    assert np.all(u >= -1 - 1e-6) and np.all(u <= 1 + 1e-6)
    assert np.ptp(u) > 1.0   # it uses the range it is given


COULOMB = {"name": "coulomb", "states": ["x", "v"], "inputs": ["u"],
           "parameters": [{"name": "c", "value": 0.5, "lower": 0.0, "upper": 100},
                          {"name": "k", "value": 4.0, "lower": 0.01, "upper": 100},
                          {"name": "Fc", "value": 0.2, "lower": 0.0, "upper": 10}],
           "equations": {"x": "v", "v": "u - c*v - k*x - Fc*tanh(v/0.01)"}, "outputs": {"y": "x"}}
QUADRATIC = {**COULOMB, "name": "quadratic",
             "parameters": COULOMB["parameters"][:2] + [{"name": "cq", "value": 0.5, "lower": 0.0, "upper": 10}],
             "equations": {"x": "v", "v": "u - c*v - k*x - cq*v*abs(v)"}}


def test_t_optimal_input_separates_coulomb_from_quadratic_damping():
    n = 101
    time = [round(0.05 * i, 10) for i in range(n)]
    base = {"name": "step", "time": time, "inputs": {"u": [0.5] * n}}
    result = design_experiment(DesignRequest.model_validate(
        {"model": COULOMB, "rivals": [{"name": "quadratic", "model": QUADRATIC}], "criterion": "T",
         "inputs": {"u": {"lower": -1.0, "upper": 1.0}}, "outputs": {"y": 0.01}, "duration": 5.0,
         "sample_time": 0.05, "hold": 0.25, "baseline": base,
         "options": {"starts": 1, "rounds": 2, "max_iterations": 40}}))
    assert {(d.truth, d.rival) for d in result.discrimination} == {("coulomb", "quadratic"),
                                                                    ("quadratic", "coulomb")}
    for d in result.discrimination:
        assert d.divergence > 2 * d.divergence_baseline
    # the reported divergence is a real refit: the rival's imitation on the designed input
    assert result.objective == pytest.approx(-min(d.divergence for d in result.discrimination))


@pytest.mark.parametrize("change, field", [
    ({"inputs": {"u": {"value": 0.5}}}, "inputs"),
    ({"inputs": {"w": {"lower": 0.0, "upper": 1.0}}}, "inputs.u"),
    ({"parameters_of_interest": ["q"]}, "parameters_of_interest"),
    ({"outputs": {"z": 0.1}}, "outputs.z"),
    ({"parameters": {"q": 1.0}}, "parameters.q"),
])
def test_bad_design_requests_name_the_field(change, field):
    with pytest.raises((DataError, ModelDefinitionError)) as info:
        design_experiment(_request(**change))
    assert info.value.field == field


def test_a_parameter_the_outputs_cannot_see_is_refused():
    model = {**MSD, "parameters": MSD["parameters"] + [{"name": "g", "value": 1.0, "lower": 0.0, "upper": 5.0}],
             "equations": {"x": "v", "v": "(u - c*v - k*x)/m", "z": "-g*z"}, "states": ["x", "v", "z"]}
    with pytest.raises(DataError) as info:
        design_experiment(_request(model=model))
    assert info.value.field == "parameters_of_interest" and "'g'" in str(info.value)


def test_a_combination_the_outputs_cannot_separate_is_refused():
    """Two tanks, the lower level measured: A1 and k1 enter only as their ratio (the pole k1/A1)."""
    tanks = {"name": "tanks", "states": ["h1", "h2"], "inputs": ["q"],
             "parameters": [{"name": "A1", "value": 1.0, "lower": 0.1, "upper": 10},
                            {"name": "k1", "value": 0.5, "lower": 0.05, "upper": 5},
                            {"name": "A2", "value": 2.0, "lower": 0.1, "upper": 10},
                            {"name": "k2", "value": 0.5, "fixed": True}],
             "equations": {"h1": "(q - k1*h1)/A1", "h2": "(k1*h1 - k2*h2)/A2"}, "outputs": {"y": "h2"}}
    with pytest.raises(DataError) as info:
        design_experiment(DesignRequest.model_validate(
            {"model": tanks, "inputs": {"q": {"lower": 0.0, "upper": 1.0}}, "outputs": {"y": 0.01},
             "duration": 20.0, "sample_time": 0.5, "options": {"starts": 1, "max_iterations": 30}}))
    assert info.value.field == "model.parameters"
    assert "A1" in str(info.value) and "k1" in str(info.value) and "A2" not in str(info.value)


@pytest.mark.parametrize("body, message", [
    ({"hold": 0.25}, "whole number of sample times"),
    ({"criterion": "T"}, "rivals"),
    ({"inputs": {"u": {"lower": 1.0, "upper": 1.0}}}, "below upper"),
    ({"outputs": {"y": 0.0}}, "positive"),
])
def test_schema_refuses_impossible_limits(body, message):
    with pytest.raises(ValueError, match=message):
        _request(**body)


def test_the_pointer_of_an_ambiguous_step_is_a_design_request_that_runs():
    """What discovery attaches to an `ambiguous` step: the fitted rivals, the record's frame as limits."""
    from greyfit.solvers.design.pointer import discrimination_request
    n = 101
    time = [round(0.05 * i, 10) for i in range(n)]
    record = {"name": "step", "time": time, "inputs": {"u": [0.5] * n}, "initial_state": {"x": 0.0, "v": 0.0}}
    sim = simulate_request(SimulateRequest.model_validate({"model": COULOMB, "experiments": [record]}))
    y = np.asarray(sim.experiments[0].outputs["y"]) + 0.01 * np.random.default_rng(3).standard_normal(n)
    fits = {}
    for model in (COULOMB, QUADRATIC):
        request = FitRequest.model_validate({"model": model, "experiments": [{**record, "outputs": {"y": list(y)}}]})
        fits[model["name"]] = (request, fit_model(request))
    (req_c, fit_c), (_, fit_q) = fits["coulomb"], fits["quadratic"]
    body = discrimination_request("coulomb", req_c.model, fit_c, req_c,
                                  [("quadratic", fits["quadratic"][0].model, fit_q)])
    # a constant input is designed between rest and the level it held; the noise is the fit's RMSE
    assert body["inputs"] == {"u": {"lower": 0.0, "upper": 0.5}}
    assert body["outputs"]["y"] == pytest.approx(fit_c.metrics.rmse["y"])
    assert body["model"]["parameters"][2]["value"] == pytest.approx(fit_c.parameters["Fc"].value)
    body["options"] = {"starts": 1, "rounds": 1, "max_iterations": 20}
    result = design_experiment(DesignRequest.model_validate(body))
    assert {d.truth for d in result.discrimination} == {"coulomb", "quadratic"}


def test_the_settle_probability_is_the_monte_carlo_rate_of_records_that_settle_the_pair():
    """A record made with the designed input settles the pair (rival's χ² above the truth's by more than
    the loop's margin) at the rate the design predicts; the margin is the loop's own."""
    from greyfit.solvers.design.criteria import SETTLE_BIC
    from greyfit.solvers.discovery.discriminate import AMBIGUOUS_BIC
    assert SETTLE_BIC == AMBIGUOUS_BIC
    sigma = 0.035   # noise chosen so that the divergence sits where the chance is neither 0 nor 1
    linear = {"name": "linear", "states": ["x", "v"], "inputs": ["u"],
              "parameters": [{"name": "c", "value": 0.8, "lower": 0, "upper": 10},
                             {"name": "k", "value": 5.0, "lower": 0, "upper": 50}],
              "equations": {"x": "v", "v": "u - c*v - k*x"}, "outputs": {"y": "x"}}
    quadratic = {**linear, "name": "quadratic", "equations": {"x": "v", "v": "u - c*v*abs(v) - k*x"}}
    result = design_experiment(DesignRequest.model_validate(
        {"model": linear, "criterion": "T", "rivals": [{"name": "quadratic", "model": quadratic}],
         "inputs": {"u": {"lower": -1.0, "upper": 1.0}}, "outputs": {"y": sigma}, "duration": 6.0,
         "sample_time": 0.1, "hold": 0.5, "initial_state": {"x": 0.0, "v": 0.0},
         "options": {"starts": 1, "rounds": 1, "max_iterations": 30}}))
    pair = next(d for d in result.discrimination if d.truth == "linear")
    assert 0.3 < pair.settle_probability < 0.97, pair
    record = result.experiment.model_dump()
    clean = np.asarray(simulate_request(SimulateRequest.model_validate(
        {"model": linear, "experiments": [record]})).experiments[0].outputs["y"])
    rng, settled, draws = np.random.default_rng(11), 0, 60
    for _ in range(draws):
        y = clean + sigma * rng.standard_normal(clean.size)
        chi2 = {}
        for model in (linear, quadratic):
            fit = fit_model(FitRequest.model_validate(
                {"model": model, "experiments": [{**record, "outputs": {"y": list(y)}}],
                 "options": {"input_interpolation": "zoh"}}))
            chi2[model["name"]] = clean.size * fit.metrics.rmse["y"] ** 2 / sigma ** 2
        settled += chi2["quadratic"] - chi2["linear"] > SETTLE_BIC
    # 60 draws: the rate's standard error is at most 0.065; the formula is first order in the refits' noise
    assert settled / draws == pytest.approx(pair.settle_probability, abs=0.17)
