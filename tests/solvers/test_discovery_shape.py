"""Shape first, say what is left: the missing term estimated without a form assumed, from outputs
only, on systems simulated with scipy (tests/partial_systems.py, tests/coloured_records.py,
tests/shape_systems.py) with known truth."""
import numpy as np
import pytest

from greyfit.schemas.discovery import DiscoverRequest
from greyfit.schemas.fit import FitRequest
from greyfit.solvers.discovery import discover
from greyfit.solvers.discovery.budget import Clock
from greyfit.solvers.discovery.ground import solid_ground
from greyfit.solvers.discovery.leftover import what_is_left
from greyfit.solvers.discovery.shape import estimate_shape
from greyfit.solvers.discovery.shape_relate import shape_agreement
from greyfit.solvers.fit import fit_model
from greyfit.solvers.simulation.simulate import validation_metrics
from tests import coloured_records as cr
from tests import partial_systems as ps
from tests import shape_systems as ss
from tests.machine_load import burning_cpu


def _fit(model, records, **options):
    req = FitRequest.model_validate({"model": model, "experiments": records, "method": "multiple_shooting",
                                     "options": options})
    return req, fit_model(req)


def _true_noise(record, level=0.01):
    y = np.array(next(iter(record["outputs"].values())))
    return level * np.std(y)   # the records' noise is level × std of the noisy output, to 0.01 %


@pytest.mark.parametrize("seed", [1, 2])
def test_shape_of_a_missing_cubic_spring_is_cubic_in_the_position(seed):
    # Duffing measured in position, declared linear: d̂ on ẏd is -k3/m y³ plus what the fitted k took
    record = cr.duffing_record(2000, seed, kind="white", level=0.01)
    req, fit = _fit(ps.duffing_model(), [record])
    shape = estimate_shape(req, fit)
    best = shape.estimates[0]
    assert best.equation == "yd"
    assert best.variable == "y" and best.share_explained > 0.9
    cubic = np.polyfit(best.variables["y"][0], best.d[0], 3)[0]
    assert cubic == pytest.approx(-ps.DUFFING_TRUTH["k3"] / ps.DUFFING_TRUTH["m"], rel=0.05)
    assert shape.noise_level["y"] == pytest.approx(_true_noise(record), rel=0.1)
    # scoring laws against the shape: the cubic has it, a switching force does not
    y, yd = best.variables["y"][0], best.variables["yd"][0]
    assert shape_agreement(best, [y ** 3]) > 0.95
    assert shape_agreement(best, [np.tanh(yd / 0.01)]) < best.share_explained - 0.3


def test_a_law_without_the_learned_shape_is_labelled_approximates():
    """Scoring laws against the shape (`shape_test.shape_note`): on the Duffing record the cubic spring
    has the shape of what is missing in the equation of ẏ; a switching force explains much less of
    it than a free smooth function of y and is labelled "approximates; not identified". A constant
    has no shape to judge."""
    from greyfit.solvers.discovery.shape_test import agreement_with_shape, shape_note
    from greyfit.solvers.screening.candidate import Candidate
    record = cr.duffing_record(2000, 1, kind="white", level=0.01)
    req, fit = _fit(ps.duffing_model(), [record])
    shape = estimate_shape(req, fit)
    best = shape.estimates[0]
    y, yd = best.variables["y"][0], best.variables["yd"][0]
    states = ["y", "yd"]

    def law(g):
        return Candidate("custom", {1: [g]}, "g", "a law", apply=lambda m: (m, []))
    assert shape_note(shape, law(y ** 3), states, ["y"]) == ""
    note = shape_note(shape, law(np.tanh(yd / (0.01 * np.std(yd)))), states, ["y"])
    assert note.startswith("approximates; not identified") and "dyd/dt" in note
    assert agreement_with_shape(shape, law(np.ones_like(y)), states, ["y"]) is None


def test_shape_of_coulomb_friction_steps_with_the_sign_of_the_speed():
    record = cr.msd_record(2000, 3, extra_force=lambda x, v: 0.5 * np.tanh(v / 1e-3))
    req, fit = _fit(cr.msd_position_model(), [record])
    best = estimate_shape(req, fit).estimates[0]
    assert best.equation == "v" and best.variable == "v"
    v, x, d = best.variables["v"][0], best.variables["x"][0], best.d[0]
    # d̂ = -Fc/m sign(v) + (what c and k took up), Fc = 0.5, m = 2; a random walk cannot jump, so the
    # switch is blurred where v crosses zero (over ~0.2 std(v)): the level is read away from there
    away = np.abs(v) > 0.5 * np.std(v)
    a = np.column_stack([np.sign(v), v, x, np.ones_like(v)])[away]
    fc_over_m = -np.linalg.lstsq(a, d[away], rcond=None)[0][0]
    assert fc_over_m == pytest.approx(0.25, rel=0.05)
    scale = np.std(v)
    friction = shape_agreement(best, [np.tanh(v / (0.1 * scale))])
    assert friction > shape_agreement(best, [x ** 3]) + 0.3
    assert friction > shape_agreement(best, [v * np.abs(v)]) + 0.1


@pytest.mark.parametrize("kind", ["white", "ar1"])
def test_a_complete_model_leaves_nothing_unexplained(kind):
    record = cr.msd_record(2000, 4, kind=kind, level=0.01, held=False)
    req, fit = _fit(cr.msd_position_model(), [record])
    shape = estimate_shape(req, fit)
    unexplained, note = what_is_left(fit, shape)
    assert unexplained is None
    if kind == "white":
        assert shape.noise_level["x"] == pytest.approx(_true_noise(record), rel=0.1)
    else:   # AR(1) ρ 0.9: a drift on the output path explains it best, and no state does
        assert "coloured measurement noise" in note


def test_before_validation_is_the_validation_records_and_absent_without_them():
    est, val = ps.speed_record(1, name="est"), ps.speed_record(51, name="val")
    body = {"model": ps.speed_model(), "method": "multiple_shooting", "experiments": [est]}
    alone = discover(DiscoverRequest.model_validate(body))
    assert alone.before.validation is None and alone.after.validation is None
    with_val = DiscoverRequest.model_validate({**body, "validation": [val]})
    res = discover(with_val)
    base = fit_model(FitRequest.model_validate(body))
    values = {n: p.value for n, p in base.parameters.items()}
    want = validation_metrics(with_val.model, values, with_val.validation, with_val.options)
    assert res.before.validation.rmse["y"] == pytest.approx(want.rmse["y"], rel=1e-6)
    assert res.before.validation.rmse["y"] != pytest.approx(res.before.rmse["y"], rel=1e-3)


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1])
def test_hysteresis_is_reported_unexplained_with_its_shape_and_nothing_named(seed):
    # seed 5 named a constant offset, seed 8 a power law v³ (after 546 s of CPU), though `unexplained`
    # was set: a law of the present variables removes a quarter of the residual's excess over the
    # noise of a disturbance no function of one variable explains; the shape test refuses it.
    # One seed here (seed 1: 52 s on the loaded machine, where 5 took 215 s and 8 186 s); the rate
    # over ten seeds, 5 and 8 among them (10 of 10 unexplained, nothing named), is
    # bench/bench_discovery.py --library's, in docs/discovery.md
    body = {"model": ss.bouc_wen_model(), "method": "multiple_shooting",
            "experiments": [ss.bouc_wen_record(seed)], "validation": [ss.bouc_wen_record(seed + 1, name="val")]}
    res = discover(DiscoverRequest.model_validate(body))
    assert res.steps == [], res.conclusion
    left = res.unexplained
    assert left is not None and left.outputs == ["y"]
    assert left.residual_to_noise["y"] > 10
    assert left.noise_level["y"] == pytest.approx(_true_noise(body["experiments"][0]), rel=0.2)
    # the restoring force's memory enters the equation of v; no function of one variable explains it
    assert left.equation == "v" and left.shape_share > 0.9
    assert left.share_explained < 0.8
    shape = res.discrepancy.equations[0]
    assert shape.equation == "v" and len(shape.samples["est"]) == len(shape.time["est"]) == 1000
    # what was refused for it, refused by the shape test or on the evidence, never by the time
    assert not [r for r in res.rejected if r.reason == "cpu_limit"], res.rejected


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1])
def test_delay_on_a_coarsely_sampled_two_lag_process(seed):
    # the screen ranks 1 and 2 samples first (its linearisation is taken where the lags have stretched
    # to mimic the delay); the refits walk along the lag to where the refit cost is least
    # (`confirm.walk_lags`). One seed of 1 000 samples here; bench/bench_discovery_delay.py runs ten of
    # 2 000 (their rate is in docs/discovery.md).
    model = ss.delay_model()
    model["parameters"][2]["value"] = 1.0   # collapsed the second lag at one RK4 step before main's fit changes
    body = {"model": model, "method": "multiple_shooting", "options": {"input_interpolation": "zoh"},
            "experiments": [ss.delay_record(seed, n=1000)],
            "validation": [ss.delay_record(seed + 1, n=1000, name="val")]}
    res = discover(DiscoverRequest.model_validate(body))
    assert res.steps and all(s.effect == "input_delay" for s in res.steps), res.conclusion
    # the input the final model reads is u shifted by the whole delay (found in one step or two)
    u = np.array(body["experiments"][0]["inputs"]["u"])
    read = np.array(res.added_inputs["est"][res.model.inputs[-1]])
    shifts = [int(np.argmin([np.abs(read[20:] - np.roll(u, s)[20:]).max() for s in range(12)]))]
    assert shifts == [ss.DELAY["delay_samples"]], res.conclusion
    p = res.fit.parameters
    # two lags in series are the same output in either order
    assert sorted([p["tau1"].value, p["tau2"].value]) == pytest.approx(
        sorted([ss.DELAY["tau1"], ss.DELAY["tau2"]]), rel=0.05)
    assert p["K"].value == pytest.approx(ss.DELAY["K"], rel=0.05)


def test_a_base_fit_that_warns_of_coarse_steps_is_refitted_with_finer_ones():
    # a fast lag (a = 2 1/s) sampled at 1 s: one RK4 step per sample is stable but inaccurate
    # (|λ|h = 2), so the fit at substeps 1 biases a; the loop refits at the substeps it suggests
    t = np.arange(400) * 1.0
    u = ss.delay_input(400, 3)
    x = ss._held(lambda s, uu: [-2.0 * s[0] + 1.0 * uu], t, [0.0], u)[0]
    y = x + 0.01 * np.std(x) * ss.noise(400, "white", 9)
    model = {"name": "lag", "states": ["x"], "inputs": ["u"], "outputs": {"y": "x"},
             "parameters": [{"name": "a", "value": 1.0, "lower": 0.0}, {"name": "b", "value": 0.5}],
             "equations": {"x": "-a*x + b*u"}}
    # substeps given: the fit keeps them (it chooses its own only when none are given)
    body = {"model": model, "method": "multiple_shooting", "options": {"input_interpolation": "zoh", "substeps": 1},
            "experiments": [{"name": "est", "time": t.tolist(), "inputs": {"u": u.tolist()},
                             "outputs": {"y": y.tolist()}}]}
    coarse = fit_model(FitRequest.model_validate(body))
    assert any(w.code == "integration_step_coarse" for w in coarse.warnings)
    res = discover(DiscoverRequest.model_validate(body))
    assert any("integration_step_coarse" in n and "substeps =" in n for n in res.notes), res.notes
    assert res.fit.parameters["a"].value == pytest.approx(2.0, rel=0.01)
    assert res.fit.parameters["b"].value == pytest.approx(1.0, rel=0.01)
    assert abs(coarse.parameters["a"].value - 2.0) > 0.01 * 2.0   # what the coarse fit gave instead


@pytest.mark.slow
def test_a_base_fit_at_a_local_minimum_is_restarted_before_screening():
    # a stiff Duffing oscillator (k = 30) in position only, single shooting from k = 10: the declared
    # linear model stops at k ≈ 60, d ≈ 0.5 (cost 262; a better linear fit has cost 213), suspect.
    # (On this record the loop also finds the cubic from the worse minimum; what is tested here is that
    # it restarts and still ends at the truth.)
    kw = dict(d=0.3, amplitude=20.0, freqs=(0.1, 0.25, 0.45, 0.7, 1.1))
    body = {"model": ss.stiff_duffing_model(10.0), "method": "single_shooting",
            "experiments": [ss.stiff_duffing_record(1, **kw)],
            "validation": [ss.stiff_duffing_record(2, name="val", **kw)]}
    res = discover(DiscoverRequest.model_validate(body))
    # before main's latest fit changes the multistart lowered the cost 262 -> 213 here; the base fit
    # may now reach the better minimum itself: the restart must run, and the search end at the truth
    assert any("multistart" in n for n in res.notes), res.notes
    assert [s.effect for s in res.steps] == ["cubic_stiffness"], res.conclusion
    p = res.fit.parameters
    assert p["k"].value == pytest.approx(30.0, rel=0.05) and p["d"].value == pytest.approx(0.3, rel=0.05)
    assert res.steps[0].parameters[0].value == pytest.approx(20.0, rel=0.05)
    assert res.unexplained is None
    # the restart is bounded by its starts and iterations: the same notes and fit, bit for bit, with
    # two CPU-burning processes beside it; its CPU limit is only a safety net, which when it ends the
    # multistart says so and keeps the base fit (it once said "found no better minimum")
    req = FitRequest.model_validate({k: body[k] for k in ("model", "method", "experiments")})
    base = fit_model(req)
    _, quiet, quiet_notes = solid_ground(req, base, Clock(1e6))
    with burning_cpu(2):
        _, loaded, loaded_notes = solid_ground(req, base, Clock(1e6))
    assert loaded_notes == quiet_notes and loaded.parameters == quiet.parameters
    assert loaded.solver.iterations == quiet.solver.iterations
    tiny = req.model_copy(update={"options": req.options.model_copy(update={"max_cpu_time": 0.01})})
    _, kept, notes = solid_ground(tiny, base, Clock(1e6))
    assert kept is base and len(notes) == 1 and "cut off by its CPU limit" in notes[0], notes
    assert "no better minimum" not in notes[0]


def test_a_law_is_compared_with_the_learned_shape_as_the_smoother_sees_it():
    """On a record whose speed reverses every few samples (a designed input), d̂ smears each jump of
    Coulomb's sign(v) over the samples around it; compared raw, the right law explained less of d̂ than
    a smooth curve and was labelled `approximates` (the loop then named Coulomb on 5 of 10 designed
    records where it beat every rival by ΔBIC 80-500). Its imprint S·g, the estimate the smoother
    makes of g itself, is what d̂ is compared with now; a wrong law ranks below it."""
    from bench.bench_design import _friction_model
    from greyfit.schemas.simulate import SimulateRequest
    from greyfit.solvers.discovery.shape_test import SHAPE_DISAGREEMENT
    from greyfit.solvers.simulation.simulate import simulate_request
    rng = np.random.default_rng(1)
    n, ts, sigma = 241, 0.05, 0.005
    t = np.round(ts * np.arange(n), 10)
    u = np.repeat(rng.uniform(-0.6, 0.6, n // 5 + 1), 5)[:n]
    record = {"name": "r", "time": t.tolist(), "inputs": {"u": u.tolist()}, "initial_state": {"x": 0.0, "v": 0.0}}
    truth = _friction_model("coulomb", 0.08)
    y = np.asarray(simulate_request(SimulateRequest.model_validate(
        {"model": truth, "experiments": [record]})).experiments[0].outputs["y"]) + sigma * rng.standard_normal(n)
    req, fit = _fit(_friction_model(None), [{**record, "outputs": {"y": y.tolist()}}])
    est = next(e for e in estimate_shape(req, fit).estimates if e.equation == "v")
    v = est.variables["v"][0]
    coulomb, quadratic = [np.tanh(v / 0.02)], [v * np.abs(v)]
    seen = shape_agreement(est, coulomb)
    assert seen >= est.share_explained - SHAPE_DISAGREEMENT + 0.2   # not `approximates`, by a margin
    # laws are told apart by refit; the right one ranks first here too
    assert seen > shape_agreement(est, quadratic) + 0.03
    imprint, est.imprint = est.imprint, None
    raw = shape_agreement(est, coulomb)
    est.imprint = imprint
    assert raw < seen - 0.3   # what the raw comparison lost
