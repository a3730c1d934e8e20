"""The covariance under an AR model of the residual (`noise_model_meat`) and the floor it puts under the
HAC standard errors (`floor_variances`), against a known AR(1) noise (issue 38)."""
from __future__ import annotations

import numpy as np

from greyfit.solvers.inference.covariance import floor_variances
from greyfit.solvers.inference.noise_model import noise_model_meat

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
    meat = noise_model_meat(jac, v, None, t, np.zeros(N, int))
    assert meat is not None
    ratio = np.diag(meat) / np.diag(truth)
    assert np.all(np.abs(ratio - 1) < 0.25), ratio
    white = np.var(v) * np.diag(jac.T @ jac)   # what a white-noise reading would say: far too small
    assert np.all(np.diag(truth) > 3 * white)


def test_a_short_series_gives_no_noise_model_meat():
    jac = np.ones((30, 2))
    assert noise_model_meat(jac, np.zeros(30), None, np.arange(30), np.zeros(30, int)) is None


def test_the_floor_raises_a_variance_and_keeps_the_correlations():
    hac = np.array([[4.0, 1.0], [1.0, 1.0]])
    by_ar = np.array([[1.0, 0.0], [0.0, 9.0]])
    cov, raised = floor_variances(hac, by_ar)
    assert raised
    assert np.allclose(np.sqrt(np.diag(cov)), [2.0, 3.0])
    corr = cov / np.sqrt(np.outer(np.diag(cov), np.diag(cov)))
    assert np.isclose(corr[0, 1], 1.0 / 2.0)
    same, raised = floor_variances(hac, 0.5 * hac)
    assert not raised and np.allclose(same, hac)
