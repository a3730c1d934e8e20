"""Candidates from the model's meaning (issue #39): every algebraically equivalent spelling of a model
gets the same couplings, the same candidates and the same screen, and no spelling raises; couplings
between bodies and nonlinear laws of an input are families of their own; labels say the law."""
import numpy as np
import pytest

from greyfit.schemas.model import Model
from greyfit.solvers.screening.canonical import canonical_form
from tests import generated_models as gm
from tests import respell as rs


def _heat(equation: str, definitions: dict | None = None) -> Model:
    return Model.model_validate({
        "states": ["T"], "inputs": ["u"], "constants": {"Ta": 295.0, "m": 1.0, "cp": 500.0},
        "parameters": [{"name": n, "value": 1.0} for n in ("U", "A", "P")],
        "definitions": definitions or {}, "equations": {"T": equation}})


@pytest.mark.parametrize("equation", [
    "U*A*(Ta - T)/(m*cp) + P*u/(m*cp)", "-U*A*(T - Ta)/(m*cp) + P*u/(m*cp)",
    "(U*A*Ta - U*A*T + P*u)/m/cp", "((Ta - T)/(1/(U*A)) + u*P)/(cp*m)", "(P*u - (T - Ta)*A*U)*(1/(m*cp))",
    "2*(-(U*(2*T/2 - Ta)*A) + P*u)/(2*m*cp)"])
def test_every_spelling_of_a_heat_loss_is_the_coupling_T_Ta(equation):
    assert [(c.equation, c.a, c.b, c.scales) for c in canonical_form(_heat(equation)).couplings] == \
        [("T", "T", "Ta", ("U", "A"))]


def test_the_couplings_of_two_bodies_are_found_in_both_equations_and_the_kinematics_by_meaning():
    body = {"states": ["zs", "vs", "zu", "vu"], "inputs": ["w"], "constants": {"ms": 2.0, "mu": 0.5},
            "parameters": [{"name": n, "value": 1.0} for n in ("ks", "cs", "kt")],
            "definitions": {"F": "ks*(zu - zs) + cs*(vu - vs)"},
            "equations": {"zs": "1*vs", "vs": "F/ms", "zu": "--vu", "vu": "(-F - kt*(zu - w))/mu"}}
    form = canonical_form(Model.model_validate(body))
    assert form.pos_of == {"vs": "zs", "vu": "zu"}
    assert {(c.equation, c.a, c.b) for c in form.couplings} == {
        ("vs", "zs", "zu"), ("vs", "vs", "vu"), ("vu", "zs", "zu"), ("vu", "vu", "vs"), ("vu", "zu", "w")}
    assert form.linear_in["ks"] == {"zs", "zu"} and form.linear_in["kt"] == {"zu", "w"}


def _fitted(kind: str, seed: int):
    from greyfit.solvers.fit import fit_model
    case = gm.generate(kind, seed)
    exp = gm.record(case, seed)
    return case, exp, fit_model(rs.request_of(case.model, exp))


@pytest.mark.parametrize("kind,seed", [("thermal", 1), ("mechanical", 2), ("fluid", 3)])
def test_random_respellings_screen_the_same_candidates(kind, seed):
    """The candidate set (effect, equation, term, where scored) and the significant ones, in the screen's
    ranking, are the same for the declared spelling and three random respellings of it, screened at the
    same fit (u² and the law P(u) of the heater tie on the thermal block: the registry's order decides)."""
    case, exp, fit = _fitted(kind, seed)
    every, significant = rs.candidate_set(case.model, exp, fit)
    assert significant, "the missing effect is seen"
    rng = np.random.default_rng(seed)
    for _ in range(3):
        spelt = rs.respell(case.model, rng)
        assert spelt["equations"] != case.model["equations"]
        assert rs.candidate_set(spelt, exp, fit) == (every, significant)


def test_a_parameter_on_one_side_of_a_difference_is_screened_without_error():
    """(T0 - th - K*q)/tau crashed the library with KeyError: 'T0' (a difference of a parameter and a
    state taken for a coupling). The fluid block drains its last tank to a level h0 alike."""
    case, exp, fit = _fitted("fluid", 1)
    assert "h0" in case.model["equations"][case.model["states"][-1]]
    every = rs.candidate_set(case.model, exp, fit)[0]
    assert every and not any(effect in ("power_law", "radiation") and "h0" in term
                             for effect, *_, term, _ in every)


def test_a_spring_between_two_bodies_is_one_coupling_law_and_a_lamp_power_an_input_law():
    """The two-body block lacks a cubic part of the spring between the bodies; the thermal block a heater
    power in u²: each is a candidate of its family, significant, and first among the significant
    candidates or within the refits' ambiguity margin (whitened ΔBIC 10) of the first (on the thermal
    block a dead zone of u, another convex law of the held input, screens 2 above u²: the refits
    tell them apart, not the screen)."""
    from greyfit.schemas.discovery import DiscoveryOptions
    from greyfit.solvers.screening.screening import screen
    for kind, seed, effect, term in (("mechanical", 2, "coupling_law", "k2 -> k2 + k2_z1_z2"),
                                     ("thermal", 1, "input_law", "+ c_u2_T1*u^2")):
        case, exp, fit = _fitted(kind, seed)
        s = screen(rs.request_of(case.model, exp), fit, DiscoveryOptions(), set())
        significant = [sc for sc in s.scored if sc.significant]
        near = [sc for sc in significant if sc.score.bic_drop > significant[0].score.bic_drop - 10.0]
        top = next((sc for sc in near if sc.candidate.effect == effect), None)
        assert top is not None and top.candidate.term.startswith(term), [sc.candidate.term for sc in near]
        if effect == "coupling_law":   # one parameter, in both bodies' equations
            assert sorted(top.candidate.equations) == [1, 3]


def test_labels_say_the_law_and_the_output_read():
    """A square-root law is not called Torricelli outflow on a model that is not a tank; sensor terms
    print what the output reads, not `h`."""
    from greyfit.schemas.discovery import DiscoveryOptions
    from greyfit.solvers.screening.screening import screen
    case, exp, fit = _fitted("thermal", 1)
    s = screen(rs.request_of(case.model, exp), fit, DiscoveryOptions(), set())
    roots = [sc.candidate for sc in s.scored if sc.candidate.effect == "sqrt_flow"]
    assert roots and all("Torricelli" not in c.description and "sqrt(T" in c.description for c in roots)
    sensors = [sc.candidate.term for sc in s.scored if sc.candidate.effect.startswith("output_")]
    assert "y_T1 = T1 + y_T1_bias" in sensors and not any(" h" in t or "(h" in t for t in sensors)


@pytest.mark.parametrize("equation", ["(F - k*x - c*v)/m", "F/m - k*x/m - c*v/m", "-(k*x - F + v*c)*(1/m)",
                                      "2*(F/2 - (k*x + c*v)/2)/m"])
def test_a_new_term_is_divided_by_what_divides_the_whole_equation_in_every_spelling(equation):
    """The new parameter is a force wherever the equation is forces over a mass, however it is spelt:
    its value (and so the refit) does not depend on the spelling."""
    from greyfit.solvers.model.compiler import compile_model
    from greyfit.solvers.screening.augment import add_term
    model = Model.model_validate({"states": ["x", "v"], "inputs": ["F"], "constants": {"m": 4.0},
                                  "parameters": [{"name": n, "value": 1.0} for n in ("k", "c", "b")],
                                  "equations": {"x": "v", "v": equation}})
    cm = compile_model(add_term(model, "v", "b*v^3", "-"))
    dv = float(cm.rhs([0.5, 2.0], [3.0], [2.0, 0.5, 1.5], 0.0)[1])
    assert dv == pytest.approx((3.0 - 2.0 * 0.5 - 0.5 * 2.0 - 1.5 * 8.0) / 4.0, rel=1e-12)
