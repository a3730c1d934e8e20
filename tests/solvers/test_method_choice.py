"""`method: auto` (the default): which shooting method runs, why, and that it is the same optimum.

Known truth throughout: data simulated from known parameters; auto's answer is compared with an
explicit multiple-shooting fit of the same request (both minimise the same simulated output
error, so their optima agree to the solver's tolerance) and with the truth.
"""
import numpy as np
import pytest

from greyfit.schemas import FitRequest
from greyfit.schemas.fit import FitMethod
from greyfit.solvers.fit import fit_model
from tests.systems import (
    MSD_TRUTH,
    SEAT_TRUTH,
    motor_inputs,
    motor_model,
    motor_truth,
    msd_experiment,
    msd_model,
    seat_experiment,
    seat_model,
    simulate_motor,
    simulate_msd,
    simulate_seat,
)

AGREE = 1e-5       # relative: auto's estimates against multiple shooting's (Ipopt tol 1e-8)


def _msd_request(c: float, k: float, t_end: float = 30.0, method: str | None = None, **options) -> dict:
    """Position-only mass-spring-damper (velocity unmeasured), bounds that admit a wrong sign."""
    t = np.arange(0.0, t_end, 0.05)
    model = msd_model(c=c, k=k)
    for p in model["parameters"]:
        if p["name"] in ("c", "k"):
            p.update(lower=-10.0, upper=100.0)
    model["outputs"] = {"x": "x"}
    body = {"model": model, "experiments": [msd_experiment(t, simulate_msd(t), noise=0.01, seed=1, outputs=("x",))],
            "options": options}
    if method is not None:
        body["method"] = method
    return body


def _motor_request(method: str | None = None) -> dict:
    t = np.linspace(0, 5, 1001)
    states, u = simulate_motor(t), motor_inputs(t)
    exp = {"name": "motor", "time": t.tolist(), "inputs": {f"u{i + 1}": u[i].tolist() for i in range(3)},
           "outputs": {f"x{i + 1}": states[i].tolist() for i in range(3)},
           "initial_state": {"x1": 0.0, "x2": 0.0, "x3": 0.0}}
    body = {"model": motor_model(), "experiments": [exp], "options": {"substeps": 4}}
    if method is not None:
        body["method"] = method
    return body


def _seat_request(method: str | None = None) -> dict:
    t, x, _, w, wd = simulate_seat(seed=0)
    guess = {k: v * (1.4 if i % 2 else 0.6) for i, (k, v) in enumerate(SEAT_TRUTH.items())}
    body = {"model": seat_model(guess), "experiments": [seat_experiment(t, x, w, wd, noise=0.01, seed=3)]}
    if method is not None:
        body["method"] = method
    return body


def _fit(body: dict):
    return fit_model(FitRequest.model_validate(body))


def _assert_same_optimum(auto, multiple):
    assert auto.success and multiple.success
    for name, p in multiple.parameters.items():
        if not p.fixed:
            assert abs(auto.parameters[name].value / p.value - 1) < AGREE, name
    # noise-free records end near cost 0, where only the absolute difference means anything
    assert abs(auto.metrics.cost - multiple.metrics.cost) < AGREE * multiple.metrics.cost + 1e-10


def test_the_default_method_is_auto_and_a_result_names_the_method_that_ran():
    body = _msd_request(0.4, 3.0)
    assert FitRequest.model_validate(body).method == FitMethod.auto
    result = _fit(body)
    assert result.solver.method == FitMethod.single_shooting
    choice = result.solver.method_choice
    assert choice is not None and choice.requested == FitMethod.auto and choice.ran == FitMethod.single_shooting
    assert not choice.fallback and "single shooting" in choice.reason
    # a named method is run as named, and the result has no choice to explain
    named = _fit(_msd_request(0.4, 3.0, method="multiple_shooting"))
    assert named.solver.method == FitMethod.multiple_shooting and named.solver.method_choice is None


@pytest.mark.parametrize("system", ["msd", "motor", pytest.param("seat", marks=pytest.mark.slow)])
def test_auto_reaches_the_multiple_shooting_optimum_and_the_truth(system):
    make, truth, tol = {"msd": (lambda m: _msd_request(0.4, 3.0, method=m), MSD_TRUTH, 0.01),
                        "motor": (_motor_request, motor_truth(), 2e-3),
                        "seat": (_seat_request, SEAT_TRUTH, 0.05)}[system]
    auto, multiple = _fit(make("auto")), _fit(make("multiple_shooting"))
    assert auto.solver.method == FitMethod.single_shooting   # stable from the start: no nodes needed
    _assert_same_optimum(auto, multiple)
    for name, value in truth.items():
        if not auto.parameters[name].fixed:
            assert abs(auto.parameters[name].value / value - 1) < tol, name


def test_a_start_that_runs_away_makes_auto_choose_multiple_shooting_and_say_so():
    # k = -3 at the start: a saddle, the simulation grows like e^(1.2 t) over 30 s (velocity unmeasured);
    # single shooting from there does not converge in 200 iterations, multiple shooting does in ~20
    auto = _fit(_msd_request(0.4, -3.0))
    choice = auto.solver.method_choice
    assert auto.solver.method == FitMethod.multiple_shooting and choice.ran == FitMethod.multiple_shooting
    assert "runs away" in choice.reason and "multiple shooting" in choice.reason and not choice.fallback
    multiple = _fit(_msd_request(0.4, -3.0, method="multiple_shooting"))
    _assert_same_optimum(auto, multiple)
    for name in ("c", "k"):
        assert abs(auto.parameters[name].value / MSD_TRUTH[name] - 1) < 0.01, name


def test_an_output_far_beyond_the_data_makes_auto_choose_multiple_shooting():
    # c = -1.5 at the start: negative damping, the simulated position reaches ~100× the measured range
    auto = _fit(_msd_request(-1.5, 3.0))
    assert auto.solver.method == FitMethod.multiple_shooting
    assert "output 'x'" in auto.solver.method_choice.reason and "measured range" in auto.solver.method_choice.reason
    _assert_same_optimum(auto, _fit(_msd_request(-1.5, 3.0, method="multiple_shooting")))


def test_an_unstable_linearisation_makes_auto_choose_multiple_shooting_even_while_the_simulation_is_small():
    # x' = a x + b u with a = +2 at the start (truth -1); u is 0 until t = 9, so the simulation from
    # x0 = 0 stays 0 until then and small after, but a perturbation would grow like e^(2·10) = e^20
    t = np.arange(0.0, 10.0, 0.01)
    u = (t >= 9.0).astype(float)
    x = np.where(t >= 9.0, 2.0 * (1.0 - np.exp(-(t - 9.0))), 0.0)   # a = -1, b = 2, exact
    body = {"model": {"name": "lag", "states": ["x"], "inputs": ["u"],
                      "parameters": [{"name": "a", "value": 2.0}, {"name": "b", "value": 1.0}],
                      "equations": {"x": "a*x + b*u"}},
            "experiments": [{"name": "e", "time": t.tolist(), "inputs": {"u": u.tolist()},
                             "outputs": {"x": x.tolist()}, "initial_state": {"x": 0.0}}],
            "options": {"input_interpolation": "zoh", "substeps": 4}}
    auto = _fit(body)
    choice = auto.solver.method_choice
    assert auto.solver.method == FitMethod.multiple_shooting
    assert "grows by e^20" in choice.reason and "unstable" in choice.reason
    assert abs(auto.parameters["a"].value + 1.0) < 1e-3 and abs(auto.parameters["b"].value - 2.0) < 2e-3


def test_single_shooting_that_fails_falls_back_to_multiple_shooting_once():
    # k = 60 at the start (truth 5): with max_iter 6 single shooting stops short (its exact-Hessian
    # polish too), multiple shooting from nodes at the data converges; its answer is kept
    body = _msd_request(0.4, 60.0, max_iter=6)
    auto = _fit(body)
    choice = auto.solver.method_choice
    assert auto.solver.method == FitMethod.multiple_shooting and choice.fallback
    assert "single shooting failed (Maximum_Iterations_Exceeded" in choice.reason
    assert "multiple shooting's answer is kept" in choice.reason
    _assert_same_optimum(auto, _fit({**body, "method": "multiple_shooting"}))


def test_shooting_interval_in_the_request_asks_for_nodes():
    auto = _fit(_msd_request(0.4, 3.0, shooting_interval=5, substeps=2))
    assert auto.solver.method == FitMethod.multiple_shooting
    assert "shooting_interval" in auto.solver.method_choice.reason


def test_the_text_report_says_which_method_ran_and_why():
    result = _fit(_msd_request(0.4, -3.0))
    text = result.report()
    assert "method:       multiple_shooting (chosen by method auto)" in text
    assert f"why:          {result.solver.method_choice.reason}" in text
    named = _fit(_msd_request(0.4, 3.0, method="single_shooting")).report()
    assert "method:       single_shooting\n" in named and "why:" not in named


@pytest.mark.slow
def test_discovery_under_auto_finds_the_missing_effect_as_multiple_shooting_does():
    # a hardening spring 20 x³ absent from the declared model; discovery refits with the request's method
    from greyfit.schemas.discovery import DiscoverRequest
    from greyfit.solvers.discovery import discover

    t = np.linspace(0, 20, 1001)
    states = simulate_msd(t, extra_force=lambda x, v: 20.0 * x ** 3)
    body = {"model": msd_model(), "experiments": [msd_experiment(t, states, noise=0.002, seed=1)]}
    found = {m: discover(DiscoverRequest.model_validate({**body, "method": m})) for m in ("auto", "multiple_shooting")}
    for m, res in found.items():
        assert [s.effect for s in res.steps] == ["cubic_stiffness"], m
        assert res.steps[0].parameters[0].value == pytest.approx(20.0, rel=0.05), m
    auto, multiple = found["auto"].fit, found["multiple_shooting"].fit
    assert auto.solver.method_choice is not None and auto.solver.method == auto.solver.method_choice.ran
    _assert_same_optimum(auto, multiple)


def test_a_fallback_cut_off_by_the_cpu_limit_is_not_kept_and_the_reason_says_so():
    """The fallback runs with the CPU time single shooting left; when that limit ends it, its answer
    (load-dependent) is not taken even where its cost is lower, and method_choice.reason says why."""
    from greyfit.solvers.methods.method_choice import fallback_reason, keep_better
    body = _msd_request(0.4, 60.0, max_iter=6)
    single = _fit({**body, "method": "single_shooting"})
    multiple = _fit({**body, "method": "multiple_shooting"})
    assert single.quality == "failed" and multiple.metrics.cost < single.metrics.cost
    cut = multiple.model_copy(update={"success": False, "quality": "failed", "solver": multiple.solver.model_copy(
        update={"return_status": "Maximum_CpuTime_Exceeded"})})
    kept = keep_better(single, cut, fallback_reason(single))
    assert kept is single and kept.solver.method == FitMethod.single_shooting and kept.solver.method_choice.fallback
    reason = kept.solver.method_choice.reason
    assert "single shooting failed (Maximum_Iterations_Exceeded" in reason
    assert "cut off by that limit (Maximum_CpuTime_Exceeded)" in reason and "options.max_cpu_time" in reason


def test_no_cpu_time_left_for_the_fallback_is_the_reason_given(monkeypatch):
    """Where single shooting used up max_cpu_time, multiple shooting does not run and the reason says so."""
    import time
    import types

    from greyfit.solvers import fit as fit_mod
    clock = iter([0.0] + [1e6] * 100)    # the fit's first look at its CPU clock, then 1e6 s later
    monkeypatch.setattr(fit_mod, "time", types.SimpleNamespace(process_time=lambda: next(clock),
                                                               perf_counter=time.perf_counter))
    auto = _fit(_msd_request(0.4, 60.0, max_iter=6))
    choice = auto.solver.method_choice
    assert auto.solver.method == FitMethod.single_shooting and not choice.fallback
    assert "single shooting failed (Maximum_Iterations_Exceeded" in choice.reason
    assert choice.reason.endswith("no CPU time is left (options.max_cpu_time) to try multiple shooting"), choice.reason


def test_an_unusable_start_names_the_first_output_and_record_that_leaves_the_measured_range():
    """The start's simulation checked against every output's measured median and range at once:
    the message names the first output (in the model's order) that leaves 10× the range, the first
    record it does so in, and the time; a sample never measured (NaN) takes no part in the range."""
    from types import SimpleNamespace

    from greyfit.solvers.methods import method_choice

    t = np.linspace(0.0, 1.0, 11)
    y1 = np.vstack([np.sin(t), np.cos(t)])
    y2 = y1.copy()
    y2[0, 3] = np.nan                                            # a missing sample of output a
    data = [SimpleNamespace(y=y1, t=t, name="r1"), SimpleNamespace(y=y2, t=t + 5.0, name="r2")]
    oem = SimpleNamespace(cm=SimpleNamespace(states=["s"], outputs=["a", "b"], ny=2), data=data)
    states = np.zeros((1, t.size))
    quiet = [(states, y1.copy()), (states, y1.copy())]
    assert method_choice._unusable(oem, quiet, []) == ""
    loud = [(states, y1.copy()), (states, y1.copy())]
    loud[1][1][1, 7] = 50.0                                       # output b, second record, t = 5.7
    loud[0][1][1, 9] = np.inf                                     # output b, first record, t = 0.9
    why = method_choice._unusable(oem, loud, [])
    assert why.startswith("output 'b' ") and "t = 0.9 " in why and "'r1'" in why
    loud[0][1][1, 9] = y1[1, 9]
    why = method_choice._unusable(oem, loud, [])
    spread = np.ptp(np.concatenate([y1[1], y2[1]]))
    centre = np.median(np.concatenate([y1[1], y2[1]]))
    assert f"{abs(50.0 - centre) / spread:.3g}×" in why and "t = 5.7 " in why and "'r2'" in why
    running = [(np.full((1, t.size), 1e300), y1), (states, y1)]
    assert "state 's'" in method_choice._unusable(oem, running, [])


def test_eigenvalues_of_repeated_blocks_are_those_of_each_block():
    """A model linear in its states has one ∂f/∂x along the whole trajectory: its eigenvalues are
    computed once, and they are what each block's own eigenvalue problem gives; distinct blocks are
    each solved."""
    from greyfit.solvers.methods.method_choice import eigenvalues

    rng = np.random.default_rng(7)
    a = rng.standard_normal((5, 5))
    same = np.repeat(a[None], 50, axis=0)
    got = eigenvalues(same)
    assert got.shape == (50, 5)
    assert all(np.array_equal(np.sort_complex(g), np.sort_complex(np.linalg.eigvals(a))) for g in got)
    mixed = same.copy()
    mixed[17] += 0.5 * np.eye(5)                     # one block shifted: its eigenvalues by 0.5
    got = eigenvalues(mixed)
    np.testing.assert_allclose(np.sort_complex(got[17]), np.sort_complex(np.linalg.eigvals(a) + 0.5), rtol=1e-12)
    np.testing.assert_allclose(np.sort_complex(got[3]), np.sort_complex(np.linalg.eigvals(a)), rtol=0)
