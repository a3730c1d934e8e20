"""The effect registry: one family per module, the schema's names equal to the registry's, and each
family a `Family` (what it supports, how it generates candidates, how it rewrites the model)."""
from typing import get_args

from greyfit.schemas.discovery import ALL_EFFECTS, Effect
from greyfit.solvers.discovery.families import BY_NAME, EFFECT_NAMES, FAMILIES, Family


def test_schema_effect_names_are_the_registry_names_in_its_order():
    assert tuple(ALL_EFFECTS) == EFFECT_NAMES
    assert set(get_args(Effect)) == set(EFFECT_NAMES)
    assert len(BY_NAME) == len(FAMILIES)   # no name given twice


def test_every_family_implements_the_protocol_and_says_what_it_supports():
    for family in FAMILIES:
        assert isinstance(family, Family), family
        assert family.scope in ("equation", "parameter", "input", "output"), family.name
        assert family.__class__.__module__.startswith("greyfit.solvers.discovery.families."), family.name
    generic = {f.name for f in FAMILIES if f.generic}
    assert generic == {"state_dependent", "input_delay"}
