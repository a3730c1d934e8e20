"""The effect registry: one family per module, the schema's names equal to the registry's, and each
family a `Family` (what it supports, how it generates candidates, how it rewrites the model)."""
from typing import get_args

import pytest

from greyfit.schemas.discovery import ALL_EFFECTS, Effect
from greyfit.schemas.model import Model
from greyfit.solvers.screening.families import BY_NAME, EFFECT_NAMES, FAMILIES, Family


def test_schema_effect_names_are_the_registry_names_in_its_order():
    assert tuple(ALL_EFFECTS) == EFFECT_NAMES
    assert set(get_args(Effect)) == set(EFFECT_NAMES)
    assert len(BY_NAME) == len(FAMILIES)   # no name given twice


def test_every_family_implements_the_protocol_and_says_what_it_supports():
    for family in FAMILIES:
        assert isinstance(family, Family), family
        assert family.scope in ("equation", "parameter", "input", "output"), family.name
        assert family.__class__.__module__.startswith("greyfit.solvers.screening.families."), family.name
    generic = {f.name for f in FAMILIES if f.generic}
    assert generic == {"state_dependent", "input_delay", "sensor_lag", "input_lag", "extra_pole", "hidden_store"}


def _screen(model: dict, record: dict, **opts):
    from greyfit.schemas.discovery import DiscoveryOptions
    from greyfit.schemas.fit import FitRequest
    from greyfit.solvers.fit import fit_model
    from greyfit.solvers.screening.screening import screen
    req = FitRequest.model_validate({"model": model, "experiments": [record], "method": "multiple_shooting",
                                     "options": {"input_interpolation": "zoh"}})
    return screen(req, fit_model(req), DiscoveryOptions(**opts), set())


def test_the_same_column_from_two_families_is_one_hypothesis_and_every_term_counts():
    """μ y² ẏ is both the power y²·ẏ and the quadratic law c(y) = c + b·y² of the damping: screened once,
    as the power (the earlier family); the Bonferroni count is the number of terms screened."""
    from tests import discovery_systems as ds
    s = _screen(ds.amplitude_damping_model(), ds.amplitude_damping_record(1, n=300),
                effects=["power_law", "parameter_law"])
    terms = [sc.candidate.term for sc in s.scored if sc.scored_on == "outputs"]
    assert any("y^2*yd" in t for t in terms)
    assert not any(t.startswith("c -> c + c_y2") for t in terms)
    assert not any(t.startswith("c -> c + c_y1") for t in terms)   # c + b·y is the power y·ẏ
    assert any(t.startswith("c -> c + c_u1") for t in terms)   # a law of the input is a column of its own
    assert s.tries >= len(s.scored)


def test_a_switch_on_the_relative_speed_of_a_state_and_an_input_is_proposed():
    """Seed 000's damper d4 switches with |q̇4 − ẇ|: a declared difference of a state and an input."""
    from greyfit.solvers.screening.families.base import declared_differences
    from tests.systems import seat_model
    pairs = {(a, b) for _, a, b in declared_differences(Model.model_validate(seat_model()))}
    assert any(b in ("w", "wd") for _, b in pairs), pairs


def test_record_specific_parameters_are_switched_off_on_validation():
    from greyfit.schemas.discovery import DiscoverRequest
    from greyfit.schemas.fit import FitRequest
    from greyfit.solvers.discovery.summary import validate
    from greyfit.solvers.fit import fit_model
    from greyfit.solvers.screening.augment import replace_parameter, with_parameter
    from tests import coloured_records as cr
    model = cr.msd_position_model()
    est, val = cr.msd_record(300, 1), cr.msd_record(300, 2, name="val", t0=6.0)
    base = fit_model(FitRequest.model_validate({"model": model, "experiments": [est]}))
    stepped = with_parameter(FitRequest.model_validate({"model": model, "experiments": [est]}).model, "dk", 3.0)
    stepped = replace_parameter(stepped, "k", "(k + dk*if_else(t >= 2, 1, 0))")
    req = DiscoverRequest.model_validate({"model": model, "experiments": [est], "validation": [val]})
    fit = fit_model(FitRequest(model=stepped, experiments=req.experiments))
    fit = fit.model_copy(update={"parameters": {**fit.parameters, "dk": fit.parameters["dk"].model_copy(
        update={"value": 3.0})}})   # a step the estimation record had
    off = validate(req, stepped, fit, req.validation, {"dk"})
    on = validate(req, stepped, fit, req.validation)
    plain = validate(req, req.model, base, req.validation)
    # the step at t = 2 s of the estimation record would act over the whole validation record (t ≥ 6 s)
    assert on.nrmse["x"] > 2 * off.nrmse["x"]
    assert off.nrmse["x"] == pytest.approx(plain.nrmse["x"], rel=0.2)
