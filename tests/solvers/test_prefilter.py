"""Seed 004: measurement noise biases ARX/RLS; the same low-pass on both sides removes most of it.

First order 200/(s+100) and second order 20000/(s^2 + 2s + 10000), T = 1 ms, input
sin(2π·2t) + 0.1 sin(2π·20t), white noise of power 1e-5, RLS with λ = 0.98 as in seed 004, the
discrete models declared in their physical parameters. The error is the mean relative error of
θ(t) over the last 5 s of a 10 s record, averaged over three noise seeds.
"""
import numpy as np
import pytest

from greyfit.schemas import FitRequest
from greyfit.solvers.fit import fit_model
from tests.online_systems import (
    FIRST_ORDER,
    SECOND_ORDER,
    first_order_model,
    second_order_model,
    seed004_experiment,
    simulate_seed004,
)

CASES = {"first_order": (FIRST_ORDER, first_order_model, {"ap": 100.0, "bp": 200.0}),
         "second_order": (SECOND_ORDER, second_order_model, {"ap1": 2.0, "ap2": 1e4, "bp2": 2e4})}


def trajectory_error(system, model, truth, seed, prefilter, method="recursive_least_squares"):
    t, u, y = simulate_seed004(system, seed=seed)
    options = {"rls": {"forgetting": 0.98, "trajectory_every": 10}}
    if prefilter:
        options["prefilter"] = {"cutoff_hz": 5.0}
    res = fit_model(FitRequest.model_validate({"model": model(), "experiments": [seed004_experiment(t, u, y)],
                                               "method": method, "options": options}))
    if method != "recursive_least_squares":
        return {k: abs(res.parameters[k].value / v - 1) for k, v in truth.items()}
    times = np.array(res.trajectory.time)
    late = times > 5.0
    return {k: float(np.mean(np.abs(np.array(res.trajectory.values[k], dtype=float)[late] / v - 1)))
            for k, v in truth.items()}


@pytest.mark.slow
@pytest.mark.parametrize("case", CASES)
def test_prefilter_at_least_halves_the_rls_parameter_error(case):
    system, model, truth = CASES[case]
    raw = [trajectory_error(system, model, truth, seed, False) for seed in range(3)]
    filtered = [trajectory_error(system, model, truth, seed, True) for seed in range(3)]
    for name in truth:
        e_raw = np.mean([r[name] for r in raw])
        e_filt = np.mean([f[name] for f in filtered])
        print(f"{case} {name}: raw {e_raw:.3e}  prefiltered {e_filt:.3e}")
        assert np.isfinite(e_filt) and e_filt <= 0.5 * e_raw, (name, e_raw, e_filt)


def test_prefilter_in_batch_equation_error_second_order():
    system, model, truth = CASES["second_order"]
    raw = trajectory_error(system, model, truth, 0, False, method="equation_error")
    filtered = trajectory_error(system, model, truth, 0, True, method="equation_error")
    # ap1 (the damping, 2 s^-1 next to 1e4) is what the noise destroys
    assert filtered["ap1"] < 0.1 and filtered["ap1"] <= 0.5 * raw["ap1"], (raw, filtered)
    assert max(filtered.values()) < 0.1


def test_state_variable_filter_is_as_good_as_savitzky_golay_in_continuous_equation_error():
    """Mass-spring-damper, x and v measured with noise 0.02 (2 % of their range), 3 seeds:
    the SVF (w/(s+w))^2 at 2 Hz against the default Savitzky-Golay derivative (window 11)."""
    from tests.systems import MSD_TRUTH, msd_experiment, msd_model, simulate_msd
    t = np.linspace(0, 20, 2001)
    states = simulate_msd(t)
    errors = {}
    for label, options in (("sg", {}), ("svf", {"prefilter": {"cutoff_hz": 2.0, "order": 2}})):
        errs = []
        for seed in range(3):
            res = fit_model(FitRequest.model_validate({
                "model": msd_model(), "method": "equation_error", "options": options,
                "experiments": [msd_experiment(t, states, noise=0.02, seed=seed)]}))
            errs.append([abs(res.parameters[k].value / MSD_TRUTH[k] - 1) for k in ("c", "k")])
        errors[label] = np.mean(errs, axis=0)
    assert "state-variable filter" in res.solver.derivative_filter
    # since Savitzky-Golay's regressors are averaged with the derivative's own kernel (#8) the two
    # are alike here (measured over 3 seeds, c and k: SG 0.41 %, 0.21 %; SVF 0.30 %, 0.27 %; SG was
    # 0.68 %, 0.56 % with the raw regressors): the SVF stays within 1 % and near SG
    assert np.all(errors["svf"] < 0.01) and np.all(errors["svf"] <= 1.5 * errors["sg"]), errors
