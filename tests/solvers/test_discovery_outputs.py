"""The discovery loop on data measured in outputs only: positions, one tank level, |speed|, the raw
EMPS encoder. Truth simulated with scipy (tests/partial_systems.py) with the effect in it, the model
declared without it, measurement noise, and a second record for validation."""
import numpy as np
import pytest

from greyfit.schemas.discovery import DiscoverRequest, DiscoveryOptions
from greyfit.schemas.fit import FitRequest
from greyfit.solvers.discovery import discover
from greyfit.solvers.discovery.loop import LoopState, try_in_rank_order
from greyfit.solvers.fit import fit_model
from greyfit.solvers.screening.screening import Scored, screen
from tests import partial_systems as ps
from tests.emps import PUBLISHED, emps_position_request
from tests.systems import msd_input, msd_model, simulate_msd

T = np.linspace(0, 20, 1001)
COULOMB = 0.5


def msd_position_record(t, seed, extra_force=None, name="est", x0=(0.1, 0.0)):
    """Position only, 1 % noise (of the position's spread)."""
    x = simulate_msd(t, x0=x0, extra_force=extra_force)[0]
    rng = np.random.default_rng(seed)
    return {"name": name, "time": t.tolist(), "inputs": {"u": msd_input(t).tolist()},
            "outputs": {"x": (x + 0.01 * np.std(x) * rng.standard_normal(t.size)).tolist()}}


def position_only_msd() -> dict:
    model = msd_model()
    model["outputs"] = {"x": "x"}
    return model


def coulomb_force(x, v):
    return COULOMB * np.tanh(v / 1e-3)


@pytest.mark.slow
def test_position_only_coulomb_is_found_and_validation_error_halves():
    body = {"model": position_only_msd(), "method": "multiple_shooting",
            "experiments": [msd_position_record(T, 1, coulomb_force)],
            "validation": [msd_position_record(T + 20.0, 2, coulomb_force, "val", x0=(-0.2, 0.1))]}
    res = discover(DiscoverRequest.model_validate(body))
    assert [s.effect for s in res.steps] == ["coulomb"], res.conclusion
    step = res.steps[0]
    assert step.equation == "v" and step.evidence.scored_on == "outputs"
    params = res.fit.parameters
    assert params["c"].value == pytest.approx(0.8, rel=0.05)
    assert params["k"].value == pytest.approx(5.0, rel=0.05)
    assert step.parameters[0].value == pytest.approx(COULOMB, rel=0.05)
    assert res.after.rmse["x"] <= 0.5 * res.before.rmse["x"]
    assert res.after.validation.rmse["x"] <= 0.5 * res.before.validation.rmse["x"]
    # the declared fit had absorbed the friction in the damping
    before = fit_model(FitRequest.model_validate({**body, "validation": []}))
    assert before.parameters["c"].value > 1.3 * 0.8


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2])
def test_duffing_measured_in_position_finds_the_cubic_spring_with_default_options(seed):
    body = {"model": ps.duffing_model(), "method": "multiple_shooting",
            "experiments": [ps.duffing_record(seed, name="est")],
            "validation": [ps.duffing_record(seed + 50, name="val")]}
    res = discover(DiscoverRequest.model_validate(body))
    assert [s.effect for s in res.steps] == ["cubic_stiffness"], (res.conclusion, res.rejected)
    assert res.steps[0].parameters[0].value == pytest.approx(ps.DUFFING_TRUTH["k3"], rel=0.05)
    assert res.fit.parameters["k"].value == pytest.approx(ps.DUFFING_TRUTH["k"], rel=0.05)
    assert res.fit.parameters["d"].value == pytest.approx(ps.DUFFING_TRUTH["d"], rel=0.05)
    assert res.after.validation.rmse["y"] < 0.2 * res.before.validation.rmse["y"]


@pytest.mark.slow
@pytest.mark.xfail(strict=False, reason=(
    'both tanks drain through orifices; in the round where √h2 is refitted beside a gain error of the '
    'level sensor both pass, the gain by ΔBIC 62 more, and it is then labelled `approximates` (it explains '
    "52 % of the learned disturbance); the orifice of h1 was refitted as a contender and stopped at the "
    "contenders' iteration cap (no verdict). Choosing among passing refits by what explains the "
    'disturbance, or refitting a capped contender in full, is open'))
def test_two_tanks_lower_level_only_sqrt_outflows_are_found():
    # single shooting: multiple shooting of this linear model from an unmeasured upper tank is the
    # degenerate case of the trust issue (#8)
    body = {"model": ps.tanks_model(), "method": "single_shooting",
            "experiments": [ps.tanks_record(1, name="est")], "validation": [ps.tanks_record(51, name="val")]}
    res = discover(DiscoverRequest.model_validate(body))
    effects = [(s.effect, s.equation) for s in res.steps]
    assert ("sqrt_flow", "h2") in effects, (res.conclusion, res.rejected)
    assert "sqrt(max(h2" in res.model.equations["h2"]
    assert res.after.validation.rmse["h2m"] < 0.5 * res.before.validation.rmse["h2m"]
    if ("sqrt_flow", "h1, h2") in effects:   # both outflows: the flow of tank 1 changes law in both equations
        assert res.fit.parameters["k1"].value == pytest.approx(ps.TANKS_TRUTH["a1"], rel=0.05)
        assert res.fit.parameters["k2"].value == pytest.approx(ps.TANKS_TRUTH["a2"], rel=0.05)


def test_sign_blind_speed_sensor_is_proposed_as_abs_output():
    body = {"model": ps.speed_model(), "method": "multiple_shooting",
            "experiments": [ps.speed_record(1, name="est")], "validation": [ps.speed_record(51, name="val")]}
    res = discover(DiscoverRequest.model_validate(body))
    assert res.steps and res.steps[0].effect == "output_abs", (res.conclusion, res.rejected)
    # and nothing piled on after it (a parameter step, a switching damping with ~0.5 % coefficients)
    assert [s.effect for s in res.steps] == ["output_abs"], res.conclusion
    assert res.model.outputs["y"] == "abs((w))"
    assert res.fit.parameters["b"].value == pytest.approx(ps.SPEED_TRUTH["b"], rel=0.02)
    assert abs(res.fit.parameters["K"].value) == pytest.approx(ps.SPEED_TRUTH["K"], rel=0.02)
    assert res.after.validation.rmse["y"] < 0.1 * res.before.validation.rmse["y"]


@pytest.mark.slow
def test_emps_from_raw_position_and_voltage_finds_coulomb_and_nothing_else_and_validates_on_pulses():
    """Coulomb friction and nothing else: the switching catch-alls that used to pile on after it (a
    friction level that rises with |v|, which took Fv to 141) make the pulses record worse and are
    refused (parsimony); M, Fv, Fc and the offset within 10 % of the published IDIM-LS values
    (Janot et al. 2019), from output error on the raw encoder position alone."""
    res = discover(DiscoverRequest.model_validate(emps_position_request()))
    assert [(s.effect, s.equation) for s in res.steps] == [("coulomb", "v")], (res.conclusion, res.rejected)
    p = res.fit.parameters
    fc = res.steps[0].parameters[0]
    assert fc.value == pytest.approx(PUBLISHED["Fc"], rel=0.10) and fc.stderr is not None
    for name in ("M", "Fv", "offset"):
        assert p[name].value == pytest.approx(PUBLISHED[name], rel=0.10), name
        assert p[name].stderr is not None
    assert res.after.validation.rmse["qm"] < 0.8 * res.before.validation.rmse["qm"]
    # refused: by parsimony, or already on its evidence (t of its coefficient under the coloured
    # residual's HAC standard error)
    assert any(r.effect == "state_dependent" and r.reason in ("parsimony", "evidence") for r in res.rejected)


@pytest.mark.slow
def test_complete_models_measured_in_outputs_get_nothing_added_over_two_seeds():
    # the rate over many seeds is bench/bench_discovery_noise.py's (position only, white, low-pass and
    # AR(1) noise, 100 seeds each), in docs/discovery-loop.md
    duffing = ps.duffing_model()
    duffing["parameters"].append({"name": "k3", "value": 1.0})
    duffing["equations"]["yd"] = "(u - d*yd - k*y - k3*y^3)/m"
    for seed in range(2):
        for body in ({"model": position_only_msd(), "experiments": [msd_position_record(T, seed)]},
                     {"model": duffing, "experiments": [ps.duffing_record(seed, n=801)]}):
            res = discover(DiscoverRequest.model_validate({**body, "method": "multiple_shooting"}))
            assert res.steps == [], (seed, body["model"]["name"], res.conclusion)
            assert res.conclusion.startswith("no significant missing effect"), res.conclusion
            assert res.model.equations == body["model"]["equations"]


def test_a_rejected_first_candidate_does_not_stop_the_real_one():
    """A spurious term ranked first (a user term sin(17.3 t), unrelated to the data, given the best
    score) is refitted, rejected on the evidence, and the next ranked candidate, the real Coulomb
    friction, is found."""
    record = msd_position_record(T, 3, coulomb_force)
    opts = DiscoveryOptions(candidates=[{"equation": "v", "term": "sin(17.3*t)", "parameter": "spurious"}])
    request = DiscoverRequest.model_validate({"model": position_only_msd(), "experiments": [record],
                                              "method": "multiple_shooting", "discovery": opts.model_dump()})
    fit_req = FitRequest(model=request.model, experiments=request.experiments, method=request.method)
    base = fit_model(fit_req)
    screening = screen(fit_req, base, opts, set())
    spurious = [s for s in screening.scored if s.candidate.effect == "custom" and s.scored_on == "outputs"][0]
    real = [s for s in screening.scored if s.candidate.effect == "coulomb" and s.significant]
    assert real
    # rank the spurious term first, above everything the screen found
    top = max(s.score.bic_drop for s in screening.scored)
    forced = Scored(spurious.candidate, spurious.score.__class__(**{**spurious.score.__dict__,
                                                                    "bic_drop": top + 1.0}), "outputs", True)
    screening.scored = [forced] + [s for s in screening.scored if s is not spurious]
    state = LoopState(request.model, fit_req, base, None, request.discovery.max_refits)
    assert try_in_rank_order(request, state, screening)
    assert state.rejected[0].effect == "custom" and state.rejected[0].reason == "evidence"
    assert [s.effect for s in state.steps] == ["coulomb"]
