"""The registries name every variant the schemas offer, and nothing else."""
import typing
from dataclasses import dataclass

import numpy as np
import pytest

from greyfit.schemas import FitRequest
from greyfit.schemas.fit import FitMethod, FitOptions
from greyfit.solvers.dynamics.integration import INTEGRATORS
from greyfit.solvers.fit import fit_model
from greyfit.solvers.methods.batch import EquationErrorFit
from greyfit.solvers.methods.registry import (
    METHODS,
    BatchMethod,
    Family,
    MethodEntry,
    OnlineMethod,
    batch_method,
    has_shooting_nodes,
    method_family,
    online_method,
    simulates_outputs,
)
from tests.systems import MSD_TRUTH, msd_experiment, msd_model, simulate_msd


def test_every_fit_method_has_one_entry_and_family():
    assert set(METHODS) == set(FitMethod)
    families = set(typing.get_args(Family))
    for m, entry in METHODS.items():
        # the entry's kind is read from what it has: a `build` (batch), a `fit` (online), or neither
        assert isinstance(entry, MethodEntry) and method_family(m) == entry.family in families
        assert (online_method(m) is not None) == isinstance(entry, OnlineMethod) == (entry.family == "online")
        if isinstance(entry, BatchMethod):
            assert entry.family in ("equation_error", "output_error") and batch_method(m) is entry
        else:
            with pytest.raises(TypeError, match="not a batch method"):
                batch_method(m)
        assert simulates_outputs(m) == (entry.family == "output_error")
    assert {method_family(m) for m in FitMethod} == families   # every family has a method
    # only multiple shooting joins pieces at nodes (auto has not chosen yet: a result names the method that ran)
    assert {m for m in FitMethod if has_shooting_nodes(m)} == {FitMethod.multiple_shooting}
    assert has_shooting_nodes("multiple_shooting") and not has_shooting_nodes("single_shooting")


@dataclass
class _CountingEquationError:
    """A new batch method as the docs add one: a class with `family`, `has_nodes` and `build`."""
    family: Family = "equation_error"
    has_nodes: bool = False
    built: int = 0

    def build(self, cm, data, layout, options):
        self.built += 1
        return EquationErrorFit.build(cm, data, layout, options)


@dataclass
class _ConstantOnline:
    family: Family = "online"
    has_nodes: bool = False

    def fit(self, request):
        raise AssertionError("not run here")


def test_a_new_method_in_a_temporary_registry_needs_no_other_edit(monkeypatch):
    new, online = _CountingEquationError(), _ConstantOnline()
    monkeypatch.setitem(METHODS, FitMethod.equation_error, new)
    monkeypatch.setitem(METHODS, FitMethod.mras, online)
    assert batch_method(FitMethod.equation_error) is new and online_method(FitMethod.equation_error) is None
    assert online_method(FitMethod.mras) is online
    # the fit outline asks the registry: the new entry builds the problem, and the fit finds the truth
    t = np.linspace(0, 20, 1001)
    body = {"model": msd_model(), "method": "equation_error",
            "experiments": [msd_experiment(t, simulate_msd(t), noise=0.0, seed=0)]}
    res = fit_model(FitRequest.model_validate(body))
    assert new.built == 1 and res.success
    for name in ("c", "k"):
        assert res.parameters[name].value == pytest.approx(MSD_TRUTH[name], rel=1e-3), name


def test_every_integrator_the_schema_offers_is_described():
    offered = set(typing.get_args(FitOptions.model_fields["integrator"].annotation))
    assert offered == set(INTEGRATORS)
    assert INTEGRATORS["rk4"].fixed_step and INTEGRATORS["rk4"].symbolic
    assert not INTEGRATORS["cvodes"].fixed_step and not INTEGRATORS["cvodes"].symbolic
