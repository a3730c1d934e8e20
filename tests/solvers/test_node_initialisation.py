"""Multiple shooting's nodes of unmeasured states start on a simulation at each start, and a start
whose simulation runs away is named in the warnings (issue #8)."""
import numpy as np
import pytest
from scipy.integrate import solve_ivp

from greyfit.schemas.fit import FitRequest
from greyfit.solvers.checks.quality import SUSPECT_CODES
from greyfit.solvers.data.experiments import prepare_experiments
from greyfit.solvers.fit import fit_model
from greyfit.solvers.methods.shooting import OutputErrorModel, build_multiple_shooting
from greyfit.solvers.model.compiler import compile_model
from greyfit.solvers.model.parameters import build_layout

T = np.linspace(0, 10, 201)


def u_of(t):
    return np.sin(1.3 * t) + 0.5 * np.sign(np.sin(0.4 * t))


def body(a0: float, multistart: int = 1) -> dict:
    """x1' = a x1 + u (unmeasured), x2' = b x1 - 2 x2 (measured); truth a = -1, b = 2."""
    sol = solve_ivp(lambda t, x: [-x[0] + u_of(t), 2.0 * x[0] - 2.0 * x[1]], (0, T[-1]), [0.0, 0.0],
                    t_eval=T, rtol=1e-10, atol=1e-12, max_step=0.02)
    y = sol.y[1] + 0.01 * np.random.default_rng(0).standard_normal(T.size)
    model = {"states": ["x1", "x2"], "inputs": ["u"],
             "parameters": [{"name": "a", "value": a0}, {"name": "b", "value": 1.0}],
             "equations": {"x1": "a*x1 + u", "x2": "b*x1 - 2*x2"}, "outputs": {"y": "x2"}}
    return {"model": model, "method": "multiple_shooting", "options": {"multistart": multistart},
            "experiments": [{"name": "e", "time": T.tolist(), "inputs": {"u": u_of(T).tolist()},
                             "outputs": {"y": y.tolist()}}]}


def test_unmeasured_nodes_follow_a_simulation_at_each_start():
    req = FitRequest.model_validate(body(-0.5))
    cm = compile_model(req.model)
    data = prepare_experiments(req.experiments, cm)
    layout = build_layout(req.model, [d.name for d in data])
    oem = OutputErrorModel(cm, data, layout, req.options)
    problem = build_multiple_shooting(oem)
    for a in (-0.5, -3.0):
        w0 = problem.initial_guess(np.array([a, 1.0]))
        x1_nodes = w0[2::2][:T.size] * oem.xscale[0]
        sol = solve_ivp(lambda t, x, a=a: [a * x[0] + np.interp(t, T, u_of(T))], (0, T[-1]), [0.0], t_eval=T,
                        rtol=1e-9, atol=1e-11, max_step=0.01)
        assert np.max(np.abs(x1_nodes - sol.y[0])) < 1e-3 * np.max(np.abs(sol.y[0]))   # RK4 vs scipy
        assert np.allclose(w0[3::2] * oem.xscale[1], data[0].y[0])   # measured: the data
    assert not oem.node_notes


@pytest.mark.parametrize("multistart", [1, 3])
def test_start_whose_simulation_runs_away_is_named_and_the_fit_recovers(multistart):
    """From a = +5 the simulation reaches 1e12 near t = 6: the nodes after that start at 0."""
    r = fit_model(FitRequest.model_validate(body(5.0, multistart)))
    assert r.parameters["a"].value == pytest.approx(-1.0, rel=0.03)
    assert r.parameters["b"].value == pytest.approx(2.0, rel=0.03)
    notes = [w for w in r.warnings if w.code == "initial_simulation_diverged" and w.detail.get("experiment")]
    assert notes and "a=5," in notes[0].message and "nodes of x1" in notes[0].message
    # the verdict's only doubt may be one of its colour tests, each run at a 0.5 % false-alarm rate
    # (seed 0's halves test: p = 0.003); nothing about the start or the nodes
    doubts = {w.code for w in r.warnings} - {"initial_simulation_diverged", "noise_model_disagrees"}
    assert r.quality in ("good", "suspect") and not doubts & set(SUSPECT_CODES), r.message
