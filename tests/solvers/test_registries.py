"""The registries name every variant the schemas offer, and nothing else."""
import typing

from greyfit.schemas.fit import FitMethod, FitOptions
from greyfit.solvers.dynamics.integration import INTEGRATORS
from greyfit.solvers.methods.registry import (
    METHODS,
    batch_method,
    has_shooting_nodes,
    method_family,
    online_method,
)


def test_every_fit_method_has_one_entry_and_family():
    assert set(METHODS) == set(FitMethod)
    assert {m: method_family(m) for m in FitMethod} == {
        FitMethod.auto: "output_error", FitMethod.equation_error: "equation_error",
        FitMethod.single_shooting: "output_error",
        FitMethod.multiple_shooting: "output_error", FitMethod.recursive_least_squares: "online",
        FitMethod.mras: "online", FitMethod.frequency_response: "frequency"}
    for m in FitMethod:
        online = online_method(m)
        assert (online is not None) == (method_family(m) == "online")
        if method_family(m) in ("equation_error", "output_error"):
            assert callable(batch_method(m).build)
    # only multiple shooting joins pieces at nodes (auto has not chosen yet: a result names the method that ran)
    assert {m for m in FitMethod if has_shooting_nodes(m)} == {FitMethod.multiple_shooting}
    assert has_shooting_nodes("multiple_shooting") and not has_shooting_nodes("single_shooting")


def test_every_integrator_the_schema_offers_is_described():
    offered = set(typing.get_args(FitOptions.model_fields["integrator"].annotation))
    assert offered == set(INTEGRATORS)
    assert INTEGRATORS["rk4"].fixed_step and INTEGRATORS["rk4"].symbolic
    assert not INTEGRATORS["cvodes"].fixed_step and not INTEGRATORS["cvodes"].symbolic
