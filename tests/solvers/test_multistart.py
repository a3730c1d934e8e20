"""Multistart agreement (issue #22): how many starts reached the best cost, and the distinct optima
the data cannot tell apart, which make a fit `suspect`. Truth simulated with scipy, outputs only,
coloured noise, a held (step) input; each case has a control where the optima are not equivalent."""
import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.signal import lfilter

from greyfit.schemas.fit import FitRequest
from greyfit.solvers.fit import fit_model
from greyfit.solvers.methods.multistart import MULTISTART_CPU_STATUS


def coloured(n: int, level: float, seed: int) -> np.ndarray:
    """AR(1) noise (pole 0.6) of standard deviation `level`."""
    e = lfilter([1.0], [1.0, -0.6], np.random.default_rng(seed).standard_normal(n))
    return level * e / np.std(e)


# --- A -> B -> C, first-order steps k1, k2 ------------------------------------------------------
def kinetics_body(measured: tuple[str, ...], seed: int = 3, multistart: int = 8, **options) -> dict:
    t = np.linspace(0, 30, 61)
    k1, k2 = 0.5, 0.2
    sol = solve_ivp(lambda _, x: [-k1 * x[0], k1 * x[0] - k2 * x[1], k2 * x[1]], (0, 30), [1, 0, 0],
                    t_eval=t, rtol=1e-11, atol=1e-13)
    outputs = {f"{s}m": (sol.y["ABC".index(s)] + coloured(t.size, 0.01, seed + i)).tolist()
               for i, s in enumerate(measured)}
    model = {"states": ["A", "B", "C"],
             "parameters": [{"name": "k1", "value": 1.0, "lower": 0.01, "upper": 3.0},
                            {"name": "k2", "value": 0.05, "lower": 0.01, "upper": 3.0}],
             "equations": {"A": "-k1*A", "B": "k1*A - k2*B", "C": "k2*B"},
             "outputs": {f"{s}m": s for s in measured}}
    return {"model": model, "method": "single_shooting",
            "options": {"multistart": multistart, "seed": 1, **options},
            "experiments": [{"time": t.tolist(), "outputs": outputs,
                             "initial_state": {"A": 1.0, "B": 0.0, "C": 0.0}}]}


def test_swapped_rates_are_listed_as_two_optima():
    """Only C measured: C(t) is symmetric in k1 and k2, both orderings fit equally well."""
    r = fit_model(FitRequest.model_validate(kinetics_body(("C",))))
    optima = r.alternative_optima
    assert optima is not None and len(optima) == 2
    pairs = sorted((o.parameters["k1"], o.parameters["k2"]) for o in optima)
    assert pairs[0] == pytest.approx((0.2, 0.5), rel=0.1) and pairs[1] == pytest.approx((0.5, 0.2), rel=0.1)
    assert abs(optima[0].cost - optima[1].cost) <= 1e-6 * optima[0].cost     # the very same cost
    assert r.solver.starts_at_best >= 2 and sum(o.starts for o in optima) <= r.solver.starts
    assert "multiple_optima" in {w.code for w in r.warnings}
    assert r.quality == "suspect" and not r.success


def test_measuring_a_breaks_the_symmetry():
    """Control: with A measured too, k1 is fixed by A alone; one optimum, no warning."""
    r = fit_model(FitRequest.model_validate(kinetics_body(("A", "C"))))
    assert r.alternative_optima is not None and len(r.alternative_optima) == 1
    assert r.parameters["k1"].value == pytest.approx(0.5, rel=0.05)
    assert r.parameters["k2"].value == pytest.approx(0.2, rel=0.05)
    assert r.solver.starts_at_best >= 2
    assert "multiple_optima" not in {w.code for w in r.warnings}


# --- second-order step response, sampled coarsely -------------------------------------------------
def step_body(dt: float, substeps: int, seed: int = 5) -> dict:
    """ωn = 4, ζ = 0.1, a unit step held from t = 0, the system already moving (v0 = 1, unknown)."""
    wn, z = 4.0, 0.1
    t = np.arange(0, 12 + 1e-9, dt)
    sol = solve_ivp(lambda _, x: [x[1], wn ** 2 * (1.0 - x[0]) - 2 * z * wn * x[1]], (0, t[-1]), [0, 1],
                    t_eval=t, rtol=1e-11, atol=1e-13)
    model = {"states": ["x", "v"], "inputs": ["u"],
             "parameters": [{"name": "wn", "value": 2.0, "lower": 1.0, "upper": 14.0},
                            {"name": "zeta", "value": 0.3, "lower": 0.005, "upper": 1.0}],
             "equations": {"x": "v", "v": "wn^2*(u - x) - 2*zeta*wn*v"}, "outputs": {"y": "x"}}
    return {"model": model, "method": "single_shooting",
            "options": {"multistart": 10, "seed": 2, "substeps": substeps, "input_interpolation": "zoh"},
            "experiments": [{"time": t.tolist(), "inputs": {"u": np.ones(t.size).tolist()},
                             "outputs": {"y": (sol.y[0] + coloured(t.size, 0.02, seed)).tolist()},
                             "initial_state": {"x": 0.0}}]}


def test_coarsely_sampled_step_lists_the_aliased_natural_frequency():
    """At 0.4 s sampling ωd and 2π/Δt − ωd give the same samples (the free initial speed takes up
    the sine's sign): ωn 4 and ≈ 11.8 are optima of indistinguishable cost."""
    r = fit_model(FitRequest.model_validate(step_body(0.4, substeps=20)))
    optima = r.alternative_optima
    assert optima is not None and len(optima) >= 2
    wns = sorted(o.parameters["wn"] for o in optima)
    wd = 4.0 * np.sqrt(1 - 0.1 ** 2)
    alias = np.hypot(2 * np.pi / 0.4 - wd, 0.4)           # same decay rate ζωn = 0.4
    assert any(abs(w - 4.0) < 0.1 for w in wns) and any(abs(w - alias) < 0.3 for w in wns)
    assert r.quality != "good" and "multiple_optima" in {w.code for w in r.warnings}


def test_finely_sampled_step_has_one_optimum():
    """Control: at 0.05 s sampling the alias lies far outside the bounds; one optimum."""
    r = fit_model(FitRequest.model_validate(step_body(0.05, substeps=2)))
    assert r.alternative_optima is not None and len(r.alternative_optima) == 1
    assert r.parameters["wn"].value == pytest.approx(4.0, rel=0.02)
    assert "multiple_optima" not in {w.code for w in r.warnings}


def test_a_single_start_reports_no_agreement():
    r = fit_model(FitRequest.model_validate(kinetics_body(("C",), multistart=1)))
    assert r.alternative_optima is None and r.solver.starts_at_best is None


def test_cpu_limit_cuts_the_multistart_off_with_a_status():
    """max_cpu_time is a safety net: a multistart it cuts short is not converged and says so."""
    r = fit_model(FitRequest.model_validate(kinetics_body(("C",), multistart=60, max_cpu_time=0.05)))
    assert r.solver.starts < 60
    assert r.solver.return_status in (MULTISTART_CPU_STATUS, "Maximum_CpuTime_Exceeded")
    assert r.quality == "failed" and not r.success


def test_a_last_start_stopped_by_the_cpu_limit_fails_the_multistart(monkeypatch):
    """The safety net inside a start's own solve: when it stops the last start, the earlier starts'
    best is not the multistart's answer (that start might have done better on a quiet machine)."""
    import dataclasses

    from greyfit.solvers.methods import multistart
    real = multistart.make_solver

    class LastCut:
        def __init__(self, solver):
            self.solver, self.compiled, self.calls = solver, solver.compiled, 0

        def solve(self, w0, lbw=None, ubw=None):
            out = self.solver.solve(w0, lbw, ubw)
            self.calls += 1
            return dataclasses.replace(out, status="Maximum_CpuTime_Exceeded", success=False) \
                if self.calls == 4 else out

    monkeypatch.setattr(multistart, "make_solver", lambda *a: LastCut(real(*a)))
    r = fit_model(FitRequest.model_validate(kinetics_body(("A", "C"), multistart=4)))
    assert r.solver.starts == 4 and r.solver.return_status == MULTISTART_CPU_STATUS
    assert r.quality == "failed" and not r.success


def test_the_exact_hessian_polish_starts_only_from_an_iterate_next_to_an_answer():
    """A Gauss-Newton solve that diverged (a cubic damping refit in discovery: multiple-shooting gaps
    of 4e10 after 20 iterations) is not polished: the polish from there spent 130 s of CPU in MUMPS'
    factorisations without a step forward. An unconverged iterate whose gaps are closed is."""
    from greyfit.schemas.fit import FitOptions
    from greyfit.solvers.methods.multistart import MultistartRun, polish_with_exact_hessian
    from greyfit.solvers.nlp.solver import NlpOutcome

    def polish_built(infeasibility: float) -> bool:
        built = []
        best = NlpOutcome(np.zeros(3), 771.0, "Maximum_Iterations_Exceeded", False, 20, 1.0, infeasibility)
        run = MultistartRun(best, [best])
        polish_with_exact_hessian(None, FitOptions(), run, exact=lambda: built.append(1))   # None: nothing to solve
        assert run.best is best and not run.polished
        return bool(built)
    assert not polish_built(4.3e10)
    assert not polish_built(float("nan"))
    assert polish_built(1e-6)
