"""Residual analysis against direct formulas and known-white / known-coloured signals."""
import numpy as np
import pytest

from greyfit.solvers.checks.diagnostics import LEVEL, _xcorr, max_abs_p_value, residual_analysis, rmse_and_fit, sidak_z


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


def _ar1(rng, n, phi):
    e = rng.standard_normal(n + 100)
    for i in range(1, e.size):
        e[i] += phi * e[i - 1]
    return e[100:]


def _smooth(rng, n):
    t = np.arange(n)
    return sum(np.sin(2 * np.pi * f * t + rng.uniform(0, 6.3)) for f in np.geomspace(1.0 / n, 0.1, 8))


def test_band_is_the_sidak_quantile_for_the_lags_tested():
    from scipy.stats import norm
    assert sidak_z(0.01, 1) == pytest.approx(norm.ppf(0.995), rel=1e-12)
    z = sidak_z(0.01, 25)
    assert (1 - 2 * norm.sf(z)) ** 25 == pytest.approx(0.99, rel=1e-12)      # all 25 lags inside: 99 %
    assert max_abs_p_value(z, 25) == pytest.approx(0.01, rel=1e-9)
    a = residual_analysis("y", [(np.zeros(1000), np.random.default_rng(0).standard_normal(1000), {})])
    assert a.whiteness.bound == pytest.approx(z / np.sqrt(1000)) and a.whiteness.level == LEVEL


def test_white_residual_false_alarms_are_at_the_family_wise_level():
    # the old per-lag 2.58/sqrt(N) band over 25 lags flagged ~21 % of white residuals (51 lags of the
    # cross-correlation ~40 %); the Sidak band flags LEVEL = 1 %: 400 runs, 4 expected, > 12 has p < 1e-3
    rng = np.random.default_rng(2)
    white = independent = 0
    p_values = []
    for _ in range(400):
        a = residual_analysis("y", [(np.zeros(500), rng.standard_normal(500), {"u": rng.standard_normal(500)})])
        white += not a.whiteness.passed
        independent += not a.independence["u"].passed
        p_values.append(a.whiteness.p_value)
        assert a.whiteness.passed == (a.whiteness.p_value > LEVEL)
    assert white <= 12 and independent <= 12
    assert 0.35 < np.mean(p_values) < 0.65          # p-values of a calibrated test: ~uniform


def test_ar1_residual_is_detected_at_500_samples():
    rng = np.random.default_rng(3)
    for phi in (0.3, 0.5):
        flagged = sum(not residual_analysis("y", [(np.zeros(500), _ar1(rng, 500, phi), {})]).whiteness.passed
                      for _ in range(50))
        assert flagged >= 48, phi        # lag-1 correlation 0.3 is 3.3 sd beyond the band 0.158


def test_coloured_residual_is_not_called_dependent_on_a_slow_input_it_does_not_depend_on():
    # a coloured residual and a slow input have a sample cross-correlation that wanders far beyond
    # 1/sqrt(N) without any dependence (the old band flagged ~65 %); the Bartlett-widened band holds
    rng = np.random.default_rng(4)
    flagged = 0
    for _ in range(100):
        a = residual_analysis("y", [(np.zeros(1000), _ar1(rng, 1000, 0.5), {"u": _smooth(rng, 1000)})])
        flagged += not a.independence["u"].passed
        assert not a.whiteness.passed
    assert flagged <= 5
    # ... while a residual that does contain the (delayed) input still fails it
    u = rng.standard_normal(1000)
    dependent = residual_analysis("y", [(np.zeros(1000), _ar1(rng, 1000, 0.5) + 0.3 * np.roll(u, 2), {"u": u})])
    assert not dependent.independence["u"].passed


def test_complete_model_fit_on_a_short_record_is_white_and_keeps_the_classical_covariance():
    # residuals of a fit are slightly correlated at short lags (projection on the p + x0 directions,
    # O(p/N)); on 201 samples of the Duffing the old band flagged 32 % of 50 seeds (at lags 11-13 in
    # seeds 4, 6, 9, 10: chance over 25 lags, the noise-free fit's residual is 1e-6) and so switched
    # `auto` to HAC; the calibrated test flagged none (bench/bench_whiteness.py)
    from greyfit.schemas import FitRequest
    from greyfit.solvers.fit import fit_model
    from tests import partial_systems as ps
    model = ps.duffing_model()
    model["parameters"] = model["parameters"] + [{"name": "k3", "value": 1.0}]
    model["equations"] = {"y": "yd", "yd": "(u - d*yd - k*y - k3*y^3)/m"}
    for seed in (0, 4, 6, 9, 10):
        r = fit_model(FitRequest.model_validate({"model": model, "experiments": [ps.duffing_record(seed, n=201)]}))
        assert r.parameters["k3"].value == pytest.approx(3.0, rel=0.02)
        assert r.residual_analysis[0].whiteness.passed, (seed, r.residual_analysis[0].whiteness)
        assert r.quality == "good" and r.covariance_classical is None     # `auto` kept the classical one


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
