"""Residual analysis against direct formulas and known-white / known-coloured signals."""
import numpy as np
import pytest

from solvers.diagnostics import _xcorr, residual_analysis, rmse_and_fit


def test_cross_correlation_matches_the_direct_sum():
    rng = np.random.default_rng(0)
    a, b = rng.standard_normal(300), rng.standard_normal(300)
    got = _xcorr(a, b, 25)
    a0, b0 = a - a.mean(), b - b.mean()
    denom = np.sqrt((a0 @ a0) * (b0 @ b0))
    for i, k in enumerate(range(-25, 26)):
        direct = np.sum(a0[k:] * b0[:300 - k]) if k >= 0 else np.sum(a0[:300 + k] * b0[-k:])
        assert got[i] == pytest.approx(direct / denom, abs=1e-12)


def test_whiteness_passes_on_white_noise_and_fails_on_coloured_noise():
    rng = np.random.default_rng(1)
    u = rng.standard_normal(2000)
    white = rng.standard_normal(2000)
    coloured = np.convolve(white, np.ones(5) / 5, mode="same")
    ok = residual_analysis("y", [(np.zeros(2000), white, {"u": u})])
    bad = residual_analysis("y", [(np.zeros(2000), coloured, {"u": u})])
    assert ok.whiteness.passed and ok.independence["u"].passed
    assert not bad.whiteness.passed
    assert bad.autocorrelation[1] == pytest.approx(0.8, abs=0.05)   # 4/5 overlap of a moving average
    # a residual that is the input itself fails the independence test
    dependent = residual_analysis("y", [(np.zeros(2000), u + 0.1 * white, {"u": u})])
    assert not dependent.independence["u"].passed


def test_fit_percent_is_matlab_nrmse():
    y = np.array([1.0, 2.0, 3.0, 4.0])
    rmse, fit = rmse_and_fit(y, np.array([0.1, -0.1, 0.1, -0.1]))
    assert rmse == pytest.approx(0.1)
    assert fit == pytest.approx(100 * (1 - 0.2 / np.sqrt(5.0)))


def test_correlations_of_an_overflowing_residual_stay_finite():
    """A diverged fit (seed 001's closed loop from a far start) left residuals near 1e200: their
    squares overflowed into NaN correlations and the result failed its own schema (a 500)."""
    rng = np.random.default_rng(0)
    r = 1e200 * rng.standard_normal(500)
    u = rng.standard_normal(500)
    a = residual_analysis("y", [(np.ones(500), r, {"u": u})])
    assert np.all(np.isfinite(a.autocorrelation)) and a.autocorrelation[0] == pytest.approx(1.0)
    assert np.isfinite(a.whiteness.max_abs) and a.whiteness.passed
    assert np.isfinite(a.independence["u"].max_abs)
