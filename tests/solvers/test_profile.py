"""Profile-likelihood intervals (`options.profile`, issue #8) against a brute-force profile and the
Wald interval."""
import dataclasses
import types

import numpy as np
import pytest
from scipy.optimize import brentq, minimize_scalar

from greyfit.schemas.fit import FitRequest
from greyfit.solvers.errors import DataError
from greyfit.solvers.fit import fit_model
from greyfit.solvers.inference.statistics import student_t_quantile
from tests.machine_load import burning_cpu

T = np.linspace(0, 3, 31)


def decay_body(y: np.ndarray, profile=("k",), method="single_shooting") -> dict:
    """y = A exp(-k t): k a parameter, A the free initial state (re-optimised along the profile)."""
    return {"model": {"states": ["x"], "parameters": [{"name": "k", "value": 1.0, "lower": 0.0}],
                      "equations": {"x": "-k*x"}, "outputs": {"y": "x"}},
            "method": method, "options": {"profile": list(profile), "substeps": 4},
            "experiments": [{"name": "e", "time": T.tolist(), "outputs": {"y": y.tolist()}}]}


def brute_force_interval(y: np.ndarray, level: float = 0.95) -> tuple[float, float, float]:
    """(k̂, lower, upper): A is linear given k, so the profile SSR(k) is exact in closed form."""
    def ssr(k):
        e = np.exp(-k * T)
        return float(np.sum((y - (e @ y) / (e @ e) * e) ** 2))
    k_hat = minimize_scalar(ssr, bounds=(0.05, 10), method="bounded", options={"xatol": 1e-12}).x
    dof = T.size - 2
    rise = student_t_quantile(0.5 + level / 2, dof) ** 2 * ssr(k_hat) / dof
    f = lambda k: ssr(k) - ssr(k_hat) - rise   # noqa: E731
    return k_hat, brentq(f, 1e-3, k_hat), brentq(f, k_hat, 50.0)


@pytest.mark.parametrize("seed", [3, 4, 5])
def test_profile_interval_matches_a_brute_force_profile_and_is_asymmetric(seed):
    rng = np.random.default_rng(seed)
    y = np.exp(-1.5 * T) + 0.1 * rng.standard_normal(T.size)
    r = fit_model(FitRequest.model_validate(decay_body(y)))
    k_hat, lower, upper = brute_force_interval(y)
    prof = r.profile["k"]
    width = upper - lower
    assert r.parameters["k"].value == pytest.approx(k_hat, abs=1e-4 * width)
    assert prof.lower == pytest.approx(lower, abs=0.005 * width)
    assert prof.upper == pytest.approx(upper, abs=0.005 * width)
    # the decay rate's profile is skewed (measured 1.17-1.33 over seeds 3-11), unlike θ ± t·stderr
    assert (upper - k_hat) > 1.1 * (k_hat - lower)
    wald = r.parameters["k"].ci95
    assert max(abs(wald[0] - lower), abs(wald[1] - upper)) > 0.03 * width
    assert prof.values == sorted(prof.values) and len(prof.values) == len(prof.costs)
    assert max(prof.costs) >= prof.threshold > min(prof.costs)


def test_multiple_shooting_profile_is_the_single_shooting_profile():
    """The nodes are re-optimised too; at each converged point the gaps are closed, so the profile
    is the same function of k."""
    y = np.exp(-1.5 * T) + 0.1 * np.random.default_rng(3).standard_normal(T.size)
    ss = fit_model(FitRequest.model_validate(decay_body(y))).profile["k"]
    ms = fit_model(FitRequest.model_validate(decay_body(y, method="multiple_shooting"))).profile["k"]
    width = ss.upper - ss.lower
    assert ms.lower == pytest.approx(ss.lower, abs=0.005 * width)
    assert ms.upper == pytest.approx(ss.upper, abs=0.005 * width)
    assert ms.note is None


def test_profile_equals_wald_interval_for_a_linear_problem():
    """Equation error of x' = -a x + b u is linear in (a, b): the profile is an exact parabola."""
    t = np.arange(1001) * 0.01
    u = np.sin(2.1 * t) + np.sign(np.sin(0.7 * t))
    rng = np.random.default_rng(0)
    x = np.zeros(t.size)
    for k in range(t.size - 1):     # exact for the input held over each interval
        x[k + 1] = np.exp(-0.01 * 2.0) * x[k] + (1 - np.exp(-0.01 * 2.0)) * 1.5 * u[k]
    x += 0.002 * rng.standard_normal(t.size)
    body = {"model": {"states": ["x"], "inputs": ["u"],
                      "parameters": [{"name": "a", "value": 1.0}, {"name": "b", "value": 1.0}],
                      "equations": {"x": "-a*x + b*u"}, "outputs": {"y": "x"}},
            "method": "equation_error",
            "options": {"profile": ["a", "b"], "input_interpolation": "zoh", "robust_covariance": "never"},
            "experiments": [{"time": t.tolist(), "inputs": {"u": u.tolist()}, "outputs": {"y": x.tolist()}}]}
    r = fit_model(FitRequest.model_validate(body))
    for name in ("a", "b"):
        lo, hi = r.parameters[name].ci95
        prof = r.profile[name]
        assert prof.lower == pytest.approx(lo, abs=0.01 * (hi - lo))
        assert prof.upper == pytest.approx(hi, abs=0.01 * (hi - lo))


def test_profile_of_an_unknown_parameter_is_a_422_naming_the_option():
    y = np.exp(-1.5 * T)
    with pytest.raises(DataError) as err:
        fit_model(FitRequest.model_validate(decay_body(y, profile=("kk",))))
    assert err.value.field == "options.profile[0]"


def test_profile_interval_covers_the_truth_about_95_percent_of_the_time():
    """60 noise draws of the decay record (noise 10 %): the profile interval holds k = 1.5."""
    hits = 0
    for seed in range(100, 160):
        y = np.exp(-1.5 * T) + 0.1 * np.random.default_rng(seed).standard_normal(T.size)
        prof = fit_model(FitRequest.model_validate(decay_body(y))).profile["k"]
        hits += prof.lower <= 1.5 <= prof.upper
    # measured 57/60 (the Wald interval 58/60); one from half the cost rise (~83 %) would fail this
    assert hits >= 53


def test_profile_interval_is_the_same_on_a_loaded_machine():
    """Determinism, not timing: the walk is bounded by its steps, so the interval and every point
    are the same, bit for bit, with two CPU-burning processes beside the fit."""
    y = np.exp(-1.5 * T) + 0.1 * np.random.default_rng(3).standard_normal(T.size)
    request = FitRequest.model_validate(decay_body(y, method="multiple_shooting"))
    quiet = fit_model(request).profile["k"]
    with burning_cpu(2):
        loaded = fit_model(request).profile["k"]
    assert loaded == quiet and quiet.lower is not None and quiet.upper is not None


class _CpuCutAfter:
    """The warm solver, its re-optimisations after the first `n` ending as Ipopt does at max_cpu_time."""

    def __init__(self, solver, n: int):
        self.solver, self.n, self.compiled = solver, n, solver.compiled

    def solve(self, w0, lbw=None, ubw=None):
        out = self.solver.solve(w0, lbw=lbw, ubw=ubw)
        self.n -= 1
        return out if self.n >= 0 else dataclasses.replace(out, status="Maximum_CpuTime_Exceeded", success=False)


@pytest.mark.parametrize("cut", ["ipopt", "profiles"])
def test_a_profile_cut_by_the_cpu_limit_is_not_computed_and_says_so(monkeypatch, cut):
    """max_cpu_time is a safety net: a re-optimisation stopped by Ipopt's CPU limit, or the profiles'
    own CPU time running out, leaves no interval (not an end that a quiet machine would find)."""
    from greyfit.solvers.inference import profile as profile_mod
    from greyfit.solvers.methods.shooting import hybrid
    y = np.exp(-1.5 * T) + 0.1 * np.random.default_rng(3).standard_normal(T.size)
    if cut == "ipopt":
        warm = hybrid.make_warm_solver
        monkeypatch.setattr(hybrid, "make_warm_solver", lambda *a: _CpuCutAfter(warm(*a), 3))
    else:
        ticks = iter(range(0, 10 ** 9, 1000))   # each look at the profiles' clock: 1000 CPU seconds later
        monkeypatch.setattr(profile_mod, "time", types.SimpleNamespace(process_time=lambda: float(next(ticks))))
    r = fit_model(FitRequest.model_validate(decay_body(y)))
    prof = r.profile["k"]
    assert prof.lower is None and prof.upper is None and prof.values == [] and prof.costs == []
    assert prof.note.startswith("not computed: the CPU limit of the profiles"), prof.note
    assert r.success and r.parameters["k"].ci95 is not None      # the fit itself is unaffected
