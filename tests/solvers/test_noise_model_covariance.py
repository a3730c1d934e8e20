"""The covariance under an AR model of the residual (`noise_model_meat`) and the floor it puts under the
HAC standard errors (`noise_model_floor`, `floor_variances`), against a known AR(1) noise and a known
noise-free error."""
from __future__ import annotations

import numpy as np

from greyfit.solvers.inference.covariance import estimate_covariance, floor_variances
from greyfit.solvers.inference.noise_model import coloured_meat, noise_model_meat
from greyfit.solvers.inference.robust_covariance import hac_meat

RHO, N = 0.8, 2000


def test_the_noise_model_meat_matches_the_true_long_run_covariance_of_ar1_noise():
    """Jᵀ Σ J for AR(1) 0.8 noise, Σ_ij = ρ^|i−j| / (1 − ρ²) for unit innovations: the meat built from an
    AR model fitted to one noise record is within 25 % of it on every entry of the diagonal."""
    rng = np.random.default_rng(3)
    t = np.arange(N)
    jac = np.column_stack([np.sin(0.01 * t), np.cos(0.003 * t), np.sign(np.sin(0.05 * t))])
    e = rng.standard_normal(N)
    v = np.empty(N)
    v[0] = e[0] / np.sqrt(1 - RHO ** 2)
    for k in range(1, N):
        v[k] = RHO * v[k - 1] + e[k]
    sigma = RHO ** np.abs(t[:, None] - t[None, :]) / (1 - RHO ** 2)
    truth = jac.T @ sigma @ jac
    model = noise_model_meat(jac, v, None, t, np.zeros(N, int))
    assert model is not None
    ratio = np.diag(model.meat) / np.diag(truth)
    assert np.all(np.abs(ratio - 1) < 0.25), ratio
    white = np.var(v) * np.diag(jac.T @ jac)   # what a white-noise reading would say: far too small
    assert np.all(np.diag(truth) > 3 * white)


def test_a_short_series_gives_no_noise_model_meat():
    jac = np.ones((30, 2))
    assert noise_model_meat(jac, np.zeros(30), None, np.arange(30), np.zeros(30, int)) is None


def test_the_floor_raises_a_variance_and_keeps_the_correlations():
    hac = np.array([[4.0, 1.0], [1.0, 1.0]])
    cov, raised = floor_variances(hac, np.array([1.0, 9.0]))
    assert raised
    assert np.allclose(np.sqrt(np.diag(cov)), [2.0, 3.0])
    corr = cov / np.sqrt(np.outer(np.diag(cov), np.diag(cov)))
    assert np.isclose(corr[0, 1], 1.0 / 2.0)
    same, raised = floor_variances(hac, 0.5 * np.diag(hac))
    assert not raised and np.allclose(same, hac)


def test_the_meat_through_sigma_times_j_is_the_lag_sum():
    rng = np.random.default_rng(0)
    jac = rng.standard_normal((300, 3))
    res = np.convolve(rng.standard_normal(320), np.ones(5) / 5, "valid")[:300]
    model = noise_model_meat(jac, res, None, np.arange(300), np.zeros(300, int))
    assert model is not None
    from greyfit.solvers.inference.noise_model import autocovariance, fit_ar
    gamma = autocovariance(*fit_ar(res))
    assert np.allclose(model.meat, coloured_meat(jac, gamma), rtol=1e-10, atol=1e-12)
    assert np.allclose(model.variance, gamma[0])


def _ar1(rng: np.random.Generator, n: int) -> np.ndarray:
    e = rng.standard_normal(n)
    v = np.empty(n)
    v[0] = e[0] / np.sqrt(1 - RHO ** 2)
    for k in range(1, n):
        v[k] = RHO * v[k - 1] + e[k]
    return v


def _robust(jac: np.ndarray, residual: np.ndarray, values: np.ndarray):
    n, k = jac.shape
    labels = [f"p{i}" for i in range(k)]
    est = estimate_covariance(jac, residual, labels, values, np.ones(k), np.ones(k, bool), k,
                              sample_keys=np.arange(n), experiment_keys=np.zeros(n, int), robust=True)
    assert est.note is not None and est.note.startswith("stderr, ci95 and covariance are HAC")
    return est, np.array([est.stderr[name] for name in labels])


def test_on_a_short_ar1_record_the_floor_raises_the_hac_standard_errors_towards_the_truth():
    """121 samples of AR(1) 0.8 noise on slow sensitivities (a decay, a rise, one period): the
    prewhitened HAC alone reads the noise as too white. Over 300 records the floor brings the
    intervals' coverage of the truth (β = 0) from below 85 % to over 87 %, and the typical variance
    from a third of the true one (exact: (XᵀX)⁻¹ Xᵀ Σ X (XᵀX)⁻¹) to at least half of it."""
    n = 121
    t = np.arange(n)
    x = np.column_stack([np.exp(-t / 30), 1 - np.exp(-t / 15), np.sin(2 * np.pi * t / n)])
    sigma = RHO ** np.abs(t[:, None] - t[None, :]) / (1 - RHO ** 2)
    inv = np.linalg.inv(x.T @ x)
    true_var = np.diag(inv @ x.T @ sigma @ x @ inv)
    rng = np.random.default_rng(1)
    covered, covered_hac, log_ratio, log_ratio_hac, raised = 0, 0, [], [], 0
    draws = 300
    for _ in range(draws):
        y = _ar1(rng, n)
        beta = inv @ x.T @ y
        r = y - x @ beta
        est, se = _robust(x, r, beta)
        meat, _ = hac_meat(x, r, t, np.zeros(n, int))
        se_hac = np.sqrt(np.diag(inv @ meat @ inv) * n / (n - 3))
        raised += bool(np.any(se > se_hac * (1 + 1e-9)))
        t95 = 1.98
        covered += int(np.sum(np.abs(beta) <= t95 * se))
        covered_hac += int(np.sum(np.abs(beta) <= t95 * se_hac))
        log_ratio.append(np.log(se ** 2 / true_var))
        log_ratio_hac.append(np.log(se_hac ** 2 / true_var))
    assert raised > draws // 2
    assert covered_hac / (3 * draws) < 0.85 < 0.87 < covered / (3 * draws)
    assert np.exp(np.mean(log_ratio_hac, axis=0))[0] < 0.4
    assert np.all(np.exp(np.mean(log_ratio, axis=0)) > 0.5)


def test_a_noise_free_fit_whose_error_sits_at_one_step_keeps_its_quiet_segments_tight():
    """A gain piecewise constant on 100 segments of 6 samples, the truth stepping from 1 to 2 inside
    segment 50 and a smooth deterministic error of 10⁻⁶ (a derivative filter's) everywhere: no
    noise. Nearly all of the residual is the step's, in six samples; a stationary AR model of it
    spreads that over the record and says the quiet segments are uncertain to about 10⁻² of their
    value, 10⁴ times what they are off by. The floor reads the residual's size where each segment
    lies: every quiet segment's standard error stays below 10⁻⁴ of its value, and the step's
    segment, which is wrong, keeps a wide one."""
    n, segments = 600, 100
    t = np.arange(n)
    width = n // segments
    x = np.sin(2 * np.pi * t / 47) + 0.5 * np.sin(2 * np.pi * t / 13.3)
    gain = np.where(t < 302, 1.0, 2.0)
    y = gain * x + 1e-6 * np.cos(2 * np.pi * t / 90)
    jac = np.zeros((n, segments))
    jac[t, t // width] = x
    inv = np.linalg.inv(jac.T @ jac)
    estimate = inv @ jac.T @ y
    r = y - jac @ estimate
    est, se = _robust(jac, r, estimate)
    truth = gain[::width]
    quiet = np.arange(segments) != 302 // width
    assert np.max(np.abs(estimate[quiet] - truth[quiet])) < 1e-5   # the quiet segments are right
    model = noise_model_meat(jac, r, None, t, np.zeros(n, int))
    assert model is not None
    stationary = np.sqrt(np.diag(inv @ model.meat @ inv))
    assert np.median(stationary[quiet] / truth[quiet]) > 1e-3   # the stationary model's size
    assert np.max(se[quiet] / truth[quiet]) < 1e-4
    assert se[~quiet][0] > 0.05 * abs(estimate[~quiet][0] - 1.5)


def test_a_parameter_that_interpolates_its_own_sample_gets_no_floor():
    """A column that is one sample's indicator (no other column there) absorbs that sample's
    residual whole: nothing of the noise's size is left to read there, and its floor is 0; the other
    column's floor is the AR model's variance to within the sampling of one record."""
    from greyfit.solvers.inference.covariance import noise_model_floor
    rng = np.random.default_rng(2)
    n = 400
    t = np.arange(n)
    alone = t == 120
    jac = np.column_stack([np.where(alone, 0.0, np.sin(2 * np.pi * t / 50)), alone.astype(float)])
    v = _ar1(rng, n)
    inv = np.linalg.inv(jac.T @ jac)
    r = v - jac @ (inv @ jac.T @ v)
    assert abs(r[120]) < 1e-12
    model = noise_model_meat(jac, r, None, t, np.zeros(n, int))
    assert model is not None
    floor = noise_model_floor(inv, jac, r, model)
    assert floor[1] == 0.0
    stationary = inv[0, 0] ** 2 * model.meat[0, 0]
    assert 0.5 * stationary < floor[0] < 2 * stationary
