"""Calibration of the RLS ±2σ band (Monte Carlo on seed 003's RL circuit, λ = 0.98).

At steady state the truth should lie inside θ̂ ± 2σ about 95 % of the time. Checked at 6 instants
(0.1 s = 5 memory lengths apart, so nearly independent) of 20 records per case.
"""
import numpy as np

from greyfit.schemas import FitRequest
from greyfit.solvers.fit import fit_model
from tests.online_systems import RL_T, RL_TRUTH, rl_experiment, rl_model, simulate_rl

RUNS, DURATION = 20, 0.8
CHECKS = np.arange(0.3, DURATION, 0.1)


def white_equation_noise_record(seed: int, level: float = 1e-3):
    """i[k+1] = a i[k] + b u[k] + w[k]: the noise RLS assumes (ARX)."""
    t, u, _ = simulate_rl(DURATION, seed=seed)
    a = np.exp(-RL_T * RL_TRUTH["R"] / RL_TRUTH["L"])
    b = (1 - a) / RL_TRUTH["R"]
    w = level * np.random.default_rng(seed + 77).standard_normal(t.size)
    i = np.zeros(t.size)
    for k in range(t.size - 1):
        i[k + 1] = a * i[k] + b * u[k] + w[k]
    return t, u, i


def band_check(records, noise: str):
    """(coverage per parameter, mean reported σ / Monte Carlo spread per parameter)."""
    inside = {n: [] for n in RL_TRUTH}
    values = {n: [] for n in RL_TRUTH}
    sigma = {n: [] for n in RL_TRUTH}
    for t, u, i in records:
        res = fit_model(FitRequest.model_validate({
            "model": rl_model(), "experiments": [rl_experiment(t, u, i)], "method": "recursive_least_squares",
            "options": {"rls": {"forgetting": 0.98, "noise": noise}}}))
        tr = res.trajectory
        idx = np.searchsorted(np.array(tr.time), CHECKS)
        for name, truth in RL_TRUTH.items():
            v, lo, hi = (np.array(x[name], dtype=float)[idx] for x in (tr.values, tr.lower, tr.upper))
            inside[name] += list((lo <= truth) & (truth <= hi))
            values[name].append(v)
            sigma[name].append((hi - lo) / 4)
    coverage = {n: float(np.mean(inside[n])) for n in RL_TRUTH}
    ratio = {n: float(np.mean(sigma[n]) / np.std(np.array(values[n]), axis=0).mean()) for n in RL_TRUTH}
    return coverage, ratio


def test_band_is_calibrated_for_white_equation_error():
    """Before: σ̂²P, too wide by about √(1+λ) (coverage 100 %); now σ̂² P (Σλ^{2(k−i)}ΦᵀΦ) P."""
    coverage, ratio = band_check([white_equation_noise_record(s) for s in range(RUNS)], "equation")
    for name in RL_TRUTH:
        assert 0.85 <= coverage[name] <= 0.99, (name, coverage)
        assert 0.7 < ratio[name] < 1.4, (name, ratio)


def test_band_is_calibrated_for_measurement_noise_with_the_measurement_noise_model():
    """Noise 1e-3 A on the measured current: the equation error is v[k+1] − a v[k] (a ≈ 0.996), nearly
    cancelling; the white-noise band is several times too wide, the moving-average one is right."""
    records = [simulate_rl(DURATION, noise=1e-3, seed=s) for s in range(RUNS)]
    coverage, ratio = band_check(records, "measurement")
    for name in RL_TRUTH:
        assert 0.85 <= coverage[name] <= 0.99, (name, coverage)
        assert 0.7 < ratio[name] < 1.4, (name, ratio)
    white_coverage, white_ratio = band_check(records[:8], "equation")
    assert min(white_coverage.values()) == 1.0 and min(white_ratio.values()) > 2.5
