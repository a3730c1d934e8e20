"""Covariance against a Monte Carlo spread; bounds, identifiability, per-experiment parameters."""
import numpy as np
import pytest

from greyfit.schemas import FitRequest
from greyfit.schemas.text_report import converged
from greyfit.solvers.fit import fit_model
from greyfit.solvers.inference.statistics import student_t_quantile
from tests.systems import MSD_TRUTH, msd_experiment, msd_model, simulate_msd

T = np.linspace(0, 10, 201)
STATES = simulate_msd(T)
NOISE = 0.01


def msd_fit(seed, method="single_shooting", **model_kw):
    model = dict(msd_model(c=0.8, k=5.0, **model_kw), outputs={"x": "x"})
    body = {"model": model, "method": method,
            "experiments": [msd_experiment(T, STATES, noise=NOISE, seed=seed, outputs=("x",))],
            "options": {"substeps": 2}}
    return fit_model(FitRequest.model_validate(body))


@pytest.mark.slow
def test_reported_stderr_matches_monte_carlo_spread():
    results = [msd_fit(seed) for seed in range(200)]
    assert all(converged(r) for r in results)
    # the verdict's tests each run at a false-alarm rate of about 0.5-1 %: a few right fits may be suspect
    assert sum(not r.success for r in results) <= 4
    for name in ("c", "k"):
        values = np.array([r.parameters[name].value for r in results])
        reported = np.mean([r.parameters[name].stderr for r in results])
        empirical = values.std(ddof=1)
        assert abs(reported / empirical - 1) < 0.30, (name, reported, empirical)
        # unbiased within the Monte Carlo error of the mean
        assert abs(values.mean() - MSD_TRUTH[name]) < 4 * empirical / np.sqrt(200)
    # 95 % intervals cover the truth about 95 % of the time
    cover = np.mean([r.parameters["k"].ci95[0] <= 5.0 <= r.parameters["k"].ci95[1] for r in results])
    assert 0.89 <= cover <= 0.99


def test_correlation_is_consistent_with_covariance():
    r = msd_fit(0)
    cov = np.array(r.covariance.matrix)
    corr = np.array(r.correlation.matrix)
    assert r.covariance.names == ["c", "k"]
    assert np.allclose(np.diag(corr), 1.0)
    assert corr[0, 1] == pytest.approx(cov[0, 1] / np.sqrt(cov[0, 0] * cov[1, 1]))
    assert r.parameters["c"].stderr == pytest.approx(np.sqrt(cov[0, 0]))


def test_parameter_on_active_bound_is_flagged_and_left_out_of_covariance():
    body = {"model": msd_model(c=1.5, k=5.0), "method": "single_shooting",
            "experiments": [msd_experiment(T, STATES, noise=NOISE, seed=1)]}
    body["model"]["parameters"][1].update(lower=1.2)   # truth c = 0.8 lies below the bound
    r = fit_model(FitRequest.model_validate(body))
    c = r.parameters["c"]
    assert c.at_bound == "lower" and c.value == pytest.approx(1.2, rel=1e-6)
    assert c.stderr is None and c.ci95 is None
    assert r.covariance.names == ["k"] and r.parameters["k"].stderr > 0


def test_unidentifiable_product_gives_null_covariance_with_the_combination():
    body = {"model": msd_model(), "method": "equation_error",
            "experiments": [msd_experiment(T, STATES, noise=NOISE, seed=2)]}
    body["model"]["parameters"] += [{"name": "k2", "value": 1.0, "lower": 0.1}]
    body["model"]["equations"]["v"] = "(u - c*v - k*k2*x)/m"
    r = fit_model(FitRequest.model_validate(body))
    assert r.covariance is None and r.correlation is None
    assert "not identifiable" in r.covariance_note
    assert "k" in r.covariance_note and "k2" in r.covariance_note
    assert r.parameters["k"].value * r.parameters["k2"].value == pytest.approx(5.0, rel=0.02)


def test_per_experiment_parameters_and_shared_ones():
    """An offset force that differs between two runs, with shared damping and stiffness."""
    exps = []
    for i, offset in enumerate([0.5, -0.3]):
        states = simulate_msd(T, extra_force=lambda x, v, o=offset: o)
        exps.append(msd_experiment(T, states, noise=0.002, seed=10 + i, name=f"run{i}"))
    model = msd_model()
    model["parameters"].append({"name": "f0", "value": 0.0, "per_experiment": True})
    model["equations"]["v"] = "(u - c*v - k*x - f0)/m"
    r = fit_model(FitRequest.model_validate({"model": model, "experiments": exps,
                                             "method": "multiple_shooting"}))
    assert r.success
    assert r.parameters["f0[run0]"].value == pytest.approx(0.5, abs=0.01)
    assert r.parameters["f0[run1]"].value == pytest.approx(-0.3, abs=0.01)
    assert r.parameters["f0[run0]"].experiment == "run0"
    assert r.parameters["c"].value == pytest.approx(0.8, rel=0.02)
    assert r.parameters["k"].value == pytest.approx(5.0, rel=0.01)
    assert set(r.initial_states) == {"run0", "run1"}


def test_general_constraint_is_respected():
    body = {"model": msd_model(c=1.5), "method": "multiple_shooting",
            "experiments": [msd_experiment(T, STATES, noise=NOISE, seed=3)]}
    body["model"]["constraints"] = ["c - 0.1*k >= 0.6"]    # truth: 0.8 - 0.5 = 0.3 violates it
    r = fit_model(FitRequest.model_validate(body))
    c, k = r.parameters["c"].value, r.parameters["k"].value
    assert c - 0.1 * k >= 0.6 - 1e-6
    assert c - 0.1 * k == pytest.approx(0.6, abs=1e-5)


def test_multistart_escapes_a_local_minimum():
    """Frequency fitting has many local minima; the best of several starts finds the truth."""
    t = np.linspace(0, 20, 401)
    x = np.cos(np.sqrt(4.0) * t)
    model = {"states": ["x", "v"], "parameters": [{"name": "k", "value": 0.3, "lower": 0.1, "upper": 10}],
             "equations": {"x": "v", "v": "-k*x"}, "outputs": {"y": "x"}}
    exp = {"time": t.tolist(), "outputs": {"y": x.tolist()}, "initial_state": {"x": 1.0, "v": 0.0}}
    single = fit_model(FitRequest.model_validate({"model": model, "experiments": [exp],
                                                  "method": "single_shooting"}))
    multi = fit_model(FitRequest.model_validate({"model": model, "experiments": [exp],
                                                 "method": "single_shooting",
                                                 "options": {"multistart": 12, "seed": 1}}))
    assert abs(single.parameters["k"].value - 4.0) > 0.1      # stuck in a local minimum
    assert multi.parameters["k"].value == pytest.approx(4.0, rel=1e-5)
    assert multi.solver.starts == 12


def test_student_t_quantile_against_tables():
    assert student_t_quantile(0.975, 1) == pytest.approx(12.706, rel=1e-4)
    assert student_t_quantile(0.975, 2) == pytest.approx(4.303, rel=1e-4)
    assert student_t_quantile(0.975, 5) == pytest.approx(2.571, rel=1e-3)
    assert student_t_quantile(0.975, 30) == pytest.approx(2.0423, rel=1e-4)
    assert student_t_quantile(0.975, 10 ** 6) == pytest.approx(1.95996, rel=1e-5)


@pytest.mark.slow
def test_stderr_holds_when_outputs_have_very_different_noise():
    """Default weights (1/std of each output) do not match the noise here (x 100x cleaner than v):
    the per-output sandwich covariance must still match the Monte Carlo spread of the estimates."""
    rng = np.random.default_rng(7)
    values, reported = {"c": [], "k": []}, {"c": [], "k": []}
    for _ in range(150):
        exp = msd_experiment(T, STATES, noise=0.0, seed=0)
        exp["outputs"]["x"] = (STATES[0] + 0.0005 * rng.standard_normal(T.size)).tolist()
        exp["outputs"]["v"] = (STATES[1] + 0.05 * rng.standard_normal(T.size)).tolist()
        res = fit_model(FitRequest.model_validate({"model": msd_model(c=0.8, k=5.0), "experiments": [exp],
                                                   "method": "single_shooting", "options": {"substeps": 2}}))
        for name in values:
            values[name].append(res.parameters[name].value)
            reported[name].append(res.parameters[name].stderr)
    for name in values:
        ratio = np.mean(reported[name]) / np.std(values[name], ddof=1)
        assert abs(ratio - 1) < 0.3, (name, ratio)


def test_non_converged_fit_is_a_result_and_non_finite_jacobian_gives_a_note():
    from greyfit.solvers.inference.covariance import estimate_covariance
    r = msd_fit(0, method="multiple_shooting")
    body = {"model": msd_model(c=0.1, k=1.0), "method": "single_shooting", "options": {"max_iter": 1},
            "experiments": [msd_experiment(T, STATES, noise=NOISE, seed=0)]}
    res = fit_model(FitRequest.model_validate(body))
    assert res.success is False and res.status == "failed"
    assert res.solver.return_status == "Maximum_Iterations_Exceeded" and "max_iter" in res.message
    assert r.success
    jac = np.array([[1.0, 0.0], [0.0, np.nan], [1.0, 1.0]])
    cov = estimate_covariance(jac, np.zeros(3), ["a", "b"], np.ones(2), np.ones(2), np.array([True, True]), 2)
    assert cov.matrix is None and "not finite" in cov.note
