"""The bounds of discovery's refits: a contender gets a multiple of its leader's iterations, every
refit a CPU safety net relative to the base fit, and a refit starts only where its model simulates.
Truth: the mass-spring-damper of bench/bench_discovery.py with Coulomb friction, and the Bouc-Wen
isolator of tests/shape_systems.py, both measured in position only."""
import numpy as np
import pytest

from greyfit.schemas.discovery import DiscoverRequest
from greyfit.schemas.fit import FitRequest
from greyfit.solvers.discovery import discover
from greyfit.solvers.discovery.budget import (
    CONTENDER_MIN_ITER,
    REFIT_CPU_FLOOR_S,
    RefitCost,
    contender_limits,
    refit_cpu_cap,
)
from greyfit.solvers.discovery.warm_start import start_is_sound
from greyfit.solvers.fit import fit_model
from tests import coloured_records as cr
from tests import shape_systems as ss


def test_a_contender_gets_a_multiple_of_the_leaders_iterations():
    assert contender_limits([RefitCost(14, 0.2, True)], 50).max_iter == 42
    assert contender_limits([RefitCost(4, 0.1, True)], 50).max_iter == CONTENDER_MIN_ITER
    assert contender_limits([RefitCost(30, 0.5, True)], 50).max_iter == 50        # never above the refit cap
    # a delay's variants: the most iterations of the converged ones, the CPU time of all
    two = contender_limits([RefitCost(9, 0.3, True), RefitCost(50, 4.0, False), RefitCost(12, 0.4, True)], 50)
    assert two.max_iter == 36 and two.max_cpu_time >= 5.0
    assert "leader" in two.reason
    assert contender_limits([RefitCost(50, 3.0, False)], 50) is None   # no reference: the refits' own caps
    assert refit_cpu_cap(0.0) == REFIT_CPU_FLOOR_S and refit_cpu_cap(2.0) == pytest.approx(40.0)


def test_a_refit_start_whose_model_blows_up_is_not_used():
    """The Gauss-Newton start of +c3·v³ on the hysteretic isolator (seed 8): c3 = 0.11 > 0 blows up in
    finite time; a refit started there spent 34 s of CPU in its first Ipopt iteration. The neutral
    start (c3 = 0) simulates as the fit does."""
    body = {"model": ss.bouc_wen_model(), "method": "multiple_shooting", "experiments": [ss.bouc_wen_record(8)]}
    req = FitRequest.model_validate(body)
    fit = fit_model(req)

    def with_cubic(c: float, k: float, c3: float):
        model = req.model.model_copy(update={"equations": {"x": "v", "v": "(u - c*v - k*x + c3*v^3)/m"}})
        values = {"c": c, "k": k, "c3": c3}
        params = [p.model_copy(update={"value": values.get(p.name, p.value)}) for p in model.parameters]
        params.append(params[-1].model_copy(update={"name": "c3", "value": c3, "lower": None}))
        return model.model_copy(update={"parameters": params})
    p = fit.parameters
    assert not start_is_sound(req, fit, with_cubic(2.3093, 0.95818, 0.11173))
    assert start_is_sound(req, fit, with_cubic(p["c"].value, p["k"].value, 0.0))


@pytest.mark.slow
def test_a_diverging_contender_does_not_spend_the_time_budget():
    """bench/bench_discovery.py's Coulomb case at 2 000 samples: a power-law contender v³ refitted
    beside the friction ran to max_cpu_time (120 s, `cpu_limit`) before the refits were bounded.
    Now every refit is decided within its bounds and the friction is found."""
    fc = 0.5

    def coulomb(x, v):
        return fc * np.tanh(v / 1e-3)
    body = {"model": cr.msd_position_model(), "method": "multiple_shooting",
            "experiments": [cr.msd_record(2000, 1, extra_force=coulomb, name="est")],
            "validation": [cr.msd_record(1000, 51, extra_force=coulomb, name="val", x0=(-0.2, 0.1), t0=40.0)]}
    res = discover(DiscoverRequest.model_validate(body))
    assert [s.effect for s in res.steps] == ["coulomb"], res.conclusion
    assert not [r for r in res.rejected if r.reason == "cpu_limit"], res.rejected
    assert res.steps[0].parameters[0].value == pytest.approx(fc, rel=0.01)


def test_the_search_budget_counts_cpu_not_wall_time():
    """A search waiting for the machine (here: sleeping) has spent none of its budget; working, it has."""
    import time

    from greyfit.solvers.discovery.budget import Clock
    clock = Clock(1.0)
    time.sleep(1.5)              # wall time passes; this process (background threads aside) works little
    assert clock.allows() and clock.left() > 0.5
    t0 = time.process_time()
    while time.process_time() - t0 < 1.1:
        pass
    assert not clock.allows() and clock.exhausted
