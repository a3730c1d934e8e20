"""The loop's decisions about catch-alls, the likelihood and time (issue 39): a catch-all whose values
follow a state points to the law of that state; a named law within the ambiguity margin goes ahead of
a catch-all; a catch-all after an approximation approximates; a profile-likelihood interval decides
where a t-value does not; a drift is carried onto a validation record that continues in time; the
solid-ground multistart is bounded relative to the base fit."""
from types import SimpleNamespace

import numpy as np
import pytest

from greyfit.schemas import FitRequest
from greyfit.schemas.discovery import DiscoverRequest
from greyfit.solvers.discovery import discover
from greyfit.solvers.discovery.budget import Clock
from greyfit.solvers.discovery.catch_all import LINE_UP, catch_all_cap, line_up, prefer_law
from greyfit.solvers.discovery.confirm import LoopState, continues_in_time, off_on_validation, profile_decides
from greyfit.solvers.discovery.ground import (
    MULTISTART_CPU_FACTOR,
    MULTISTART_CPU_FLOOR_S,
    MULTISTART_MIN_ITER,
    multistart_bounds,
)
from greyfit.solvers.fit import fit_model
from greyfit.solvers.screening.effects import Candidate
from greyfit.solvers.screening.scoring import RegressionScorer
from greyfit.solvers.screening.screening import Scored
from tests.suite_systems import noisy, simulate


class _Columns(RegressionScorer):
    """A regression whose candidate columns are given directly (one experiment, one equation)."""

    def stack(self, regressor, outputs=None):
        return np.column_stack(regressor[0]) if len(regressor[0]) > 1 else regressor[0][0]


def _cand(effect: str, columns: list[np.ndarray], **kw) -> Candidate:
    return Candidate(effect, {0: columns}, effect, effect, lambda m: (m, []), family=effect, **kw)


def test_steps_that_follow_a_state_line_up_with_its_law_and_not_with_another():
    rng = np.random.default_rng(3)
    n = 1200
    t = np.arange(n) * 0.1
    temp = np.cumsum(rng.normal(size=n)) * 0.1          # a slowly wandering state
    other = np.sin(2 * np.pi * t / 7.0)                  # a variable the residual does not follow
    residual = 0.5 * (temp - temp.mean()) + rng.normal(scale=0.05, size=n)
    scorer = _Columns(residual, np.ones((n, 1)))
    switch_times = np.quantile(t, np.linspace(0.1, 0.9, 6))
    steps = _cand("parameter_step", [(t >= tau).astype(float) for tau in switch_times], record_specific=True)
    law_t = _cand("parameter_law", [temp])
    law_other = _cand("parameter_law", [other])
    sc = [Scored(c, None, "equations", scorer=scorer) for c in (steps, law_t, law_other)]
    assert line_up(sc[0], sc[1]) > LINE_UP
    assert line_up(sc[0], sc[2]) < 0.3


def _refit(catch_all: bool):
    c = _cand("parameter_step" if catch_all else "radiation", [np.ones(3)], record_specific=catch_all)
    return SimpleNamespace(sc=SimpleNamespace(candidate=c))


def test_a_named_law_within_the_margin_goes_ahead_of_a_catch_all():
    kept = [_refit(True), _refit(False), _refit(False)]
    assert prefer_law([0, 1, 2], kept, [100.0, 104.0, 120.0], 10.0) == [1, 0, 2]
    assert prefer_law([0, 1, 2], kept, [100.0, 115.0, 120.0], 10.0) == [0, 1, 2]   # the data tell them apart
    assert prefer_law([1, 0, 2], kept, [100.0, 90.0, 120.0], 10.0) == [1, 0, 2]    # a law leads already


def test_a_catch_all_after_an_approximation_approximates():
    state = SimpleNamespace(steps=[SimpleNamespace(verdict="approximates", effect="power_law")])
    verdict, note = catch_all_cap(state, _refit(True), "identified", [])
    assert verdict == "approximates" and "power_law" in note
    assert catch_all_cap(state, _refit(False), "identified", []) == ("identified", "")
    assert catch_all_cap(SimpleNamespace(steps=[]), _refit(True), "identified", []) == ("identified", "")


# --- a first-order thermal block: dT/dt = a*u - b*T ---------------------------------------------------

A, B = 1.2, 0.5


def _held_input(seed: int, n: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.repeat(rng.uniform(0.2, 2.0, n // 40 + 1), 40)[:n]


def _record(name, t, u, x0, drift, seed):
    x = simulate(lambda tt, s, uu: [A * (1 + drift * tt) * uu - B * s[0]], t, [x0], u, True)
    return {"name": name, "time": t.tolist(), "inputs": {"u": u.tolist()},
            "outputs": {"T": noisy(x[0], "white", seed, level=0.01)}}, float(x[0, -1])


def _model(extra: str = "") -> dict:
    return {"states": ["T"], "inputs": ["u"], "outputs": {"T": "T"},
            "parameters": [{"name": "a", "value": 1.0, "lower": 0}, {"name": "b", "value": 0.6, "lower": 0},
                           *([{"name": "f", "value": 0.0}] if extra else [])],
            "equations": {"T": f"a*u - b*T{extra}"}}


def _body(drift: float, continues: bool, n: int = 600, dt: float = 0.1):
    t = np.arange(n) * dt
    est, x_end = _record("est", t, _held_input(1, n), 0.0, drift, 11)
    t_val = t + n * dt if continues else t
    val, _ = _record("val", t_val, _held_input(2, n), x_end if continues else 0.0, drift, 12)
    return {"model": _model(), "experiments": [est], "validation": [val], "method": "single_shooting",
            "options": {"input_interpolation": "zoh"}}


def test_a_validation_record_that_continues_in_time_keeps_the_time_laws_on():
    state = SimpleNamespace(record_params={"da_dt", "da_step"}, time_params={"da_dt"})
    cont = DiscoverRequest.model_validate(_body(0.0, True, n=50))
    restart = DiscoverRequest.model_validate(_body(0.0, False, n=50))
    assert continues_in_time(cont) and not continues_in_time(restart)
    assert off_on_validation(cont, state, set()) == {"da_step"}
    assert off_on_validation(restart, state, set()) == {"da_dt", "da_step"}
    assert off_on_validation(cont, state, {"db_dt"}, new_in_time=True) == {"da_step"}


@pytest.mark.slow
def test_a_drift_is_confirmed_on_a_validation_record_that_continues_it():
    # the heater's gain grows 0.6 %/s: 36 % over the estimation record, and on through the validation
    res = discover(DiscoverRequest.model_validate({**_body(0.006, True), "discovery": {"max_terms": 1}}))
    assert [s.effect for s in res.steps] == ["parameter_drift"], res.conclusion
    drift = res.steps[0]
    assert "a" in drift.term
    # a(t) = a + d*(t - t̄): d = A*0.006 = 0.0072 per s
    assert drift.parameters[0].value == pytest.approx(A * 0.006, rel=0.1)
    assert res.after.validation.nrmse["T"] < 0.5 * res.before.validation.nrmse["T"]


def _state_for(req: FitRequest) -> LoopState:
    fit = fit_model(req)
    return LoopState(req.model, req, fit, None, refits_left=5, clock=Clock(120.0), base_cpu_s=1.0)


def test_the_profile_likelihood_decides_a_coefficient_by_its_interval():
    exp = _body(0.0, False, n=300)["experiments"][0]
    # a constant source f: truly 0 here, so its interval reaches 0; with 0.3 added to the truth it does not
    req0 = FitRequest.model_validate({"model": _model(" + f"), "experiments": [exp],
                                      "method": "single_shooting", "options": {"input_interpolation": "zoh"}})
    state = _state_for(req0)
    assert profile_decides(state, req0, state.fit, ["f"], 1e-3) == ""
    t = np.array(exp["time"])
    x = simulate(lambda tt, s, uu: [A * uu - B * s[0] + 0.3], t, [0.0], np.array(exp["inputs"]["u"]), True)
    with_source = {**exp, "outputs": {"T": noisy(x[0], "white", 11, level=0.01)}}
    req1 = req0.model_copy(update={"experiments": [req0.experiments[0].model_validate(with_source)]})
    state = _state_for(req1)
    note = profile_decides(state, req1, state.fit, ["f"], 1e-3)
    assert "excludes 0" in note and state.refits_left == 4
    lo, hi = (float(v) for v in note.split("[")[1].split("]")[0].split(","))
    assert lo < 0.3 < hi and lo > 0


def test_the_multistart_is_bounded_relative_to_the_base_fit():
    req = FitRequest.model_validate({"model": _model(), "experiments": [_body(0.0, False, n=50)["experiments"][0]]})
    base = SimpleNamespace(solver=SimpleNamespace(iterations=12))
    cpu, iters = multistart_bounds(req, base, Clock(300.0), base_cpu_s=4.0)
    assert cpu == pytest.approx(MULTISTART_CPU_FACTOR * 4.0) and cpu < 300.0 and iters == 36
    cpu, iters = multistart_bounds(req, SimpleNamespace(solver=SimpleNamespace(iterations=2)), Clock(300.0), 0.1)
    assert cpu == pytest.approx(MULTISTART_CPU_FLOOR_S) and iters == MULTISTART_MIN_ITER


def test_laws_the_screen_dropped_with_a_large_gain_are_refitted_best_per_family():
    from greyfit.schemas.discovery import DiscoveryOptions
    from greyfit.solvers.discovery.loop import BELOW_SCREEN_REFITS, below_screen
    from greyfit.solvers.screening.scoring import Score
    from greyfit.solvers.screening.screening import Screening

    def scored(family, bic_drop, beta=1.0, significant=False, sign=1.0, **kw):
        c = Candidate(family, {0: [np.ones(3)]}, f"{family} {bic_drop}", family, lambda m: (m, []), family=family,
                      sign=sign, **kw)
        return Scored(c, Score(1.0, 0.5, 100, 80.0, 0.3, 5.0, 0.04, bic_drop, beta, 0.5), "outputs",
                      significant=significant)
    screen = Screening(scored=[
        scored("radiation", 581.0), scored("radiation", 300.0),          # its family's best only
        scored("coulomb", 40.0), scored("quadratic_drag", 25.0, beta=-1.0),   # unphysical sign: no
        scored("offset", 5.0),                                            # too little gain
        scored("parameter_step", 900.0, record_specific=True),            # a catch-all: never here
        scored("cubic_stiffness", 900.0, significant=True),               # the screen's own business
        scored("power_law", 30.0), scored("sqrt_flow", 20.0)])
    picked = below_screen(screen, {"power_law"}, DiscoveryOptions())
    assert [s.candidate.term for s in picked] == ["radiation 581.0", "coulomb 40.0", "sqrt_flow 20.0"]
    assert len(picked) == BELOW_SCREEN_REFITS


def test_a_delay_is_refitted_beside_every_lag_the_library_offers():
    from greyfit.solvers.discovery.catch_all import pointed_candidates
    from greyfit.solvers.screening.scoring import Score
    from greyfit.solvers.screening.screening import Screening

    def scored(effect, explained, **kw):
        c = Candidate(effect, {0: [np.ones(3)]}, effect, effect, lambda m: (m, []), family=effect, **kw)
        return Scored(c, Score(1.0, 0.5, 100, 80.0, explained, 5.0, 1e-6, 50.0, 1.0, 0.5), "outputs")
    delay = scored("input_delay", 0.6, generic=True, lag=3)
    screen = Screening(scored=[delay, scored("sensor_lag", 0.4, generic=True), scored("input_lag", 0.5, generic=True),
                               scored("coulomb", 0.55), scored("parameter_step", 0.7, record_specific=True)])
    offered = pointed_candidates(delay, screen, set())
    assert [sc.candidate.effect for sc, _ in offered] == ["input_lag", "sensor_lag"]
    assert pointed_candidates(delay, screen, {"input_lag"})[0][0].candidate.effect == "sensor_lag"
