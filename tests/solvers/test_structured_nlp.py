"""The structured shooting NLP (solvers/methods/shooting/structured.py) evaluates the same f, g and
derivatives as CasADi's own differentiation of the generic graph.

Truth: `ca.jacobian` of the generic graph's residual and gaps. The case exercises what the block
assembly can get wrong: records that are no whole number of blocks (padding), two experiments with a
per-experiment parameter, a known and a free initial state, masked samples, an output that depends
on a parameter (θ-node Hessian blocks) and a parameter that no output depends on (structural zeros
in the gradient, which Ipopt's interface would fill with stale memory if left sparse).
"""
import casadi as ca
import numpy as np
import pytest

from greyfit.schemas.fit import FitRequest
from greyfit.solvers.data.experiments import prepare_experiments
from greyfit.solvers.methods.shooting import OutputErrorModel, build_multiple_shooting, build_single_shooting
from greyfit.solvers.model.compiler import compile_model
from greyfit.solvers.model.parameters import build_layout


def _body(method: str, output_gain: bool) -> dict:
    """`output_gain`: y = s·x with a parameter s, else y = x (no output depends on a parameter)."""
    t = np.linspace(0, 5, 61)   # 61 samples: one whole block of 32 and a padded one
    model = {"states": ["x", "v"], "inputs": ["u"],
             "parameters": [{"name": "c", "value": 0.5}, {"name": "k", "value": 2.0},
                            {"name": "g", "value": 1.0, "per_experiment": True}],
             "equations": {"x": "v", "v": "g*u - c*v*abs(v) - k*x - 0.3*k*x^3"},
             "outputs": {"y": "x", "z": "v"}, "constraints": ["k - c*c >= 0"]}
    if output_gain:
        model["parameters"].append({"name": "s", "value": 1.2})
        model["outputs"]["y"] = "s*x"
    exps = []
    for i in range(2):
        y = 0.1 * np.sin(0.7 * t + i)
        exps.append({"name": f"e{i}", "time": t.tolist(), "inputs": {"u": np.sin((1 + i) * t).tolist()},
                     "outputs": {"y": [None if k % 9 == 4 else v for k, v in enumerate(y)],
                                 "z": (0.07 * np.cos(0.7 * t + i)).tolist()}})
    exps[1]["initial_state"] = {"v": 0.2}
    return {"model": model, "experiments": exps, "method": method}


def _oem(body) -> OutputErrorModel:
    req = FitRequest.model_validate(body)
    cm = compile_model(req.model)
    data = prepare_experiments(req.experiments, cm)
    return OutputErrorModel(cm, data, build_layout(req.model, [d.name for d in data]), req.options)


def _reference(p):
    """(f, g, ∇f, ∂g/∂w, triu(JᵀJ)) of the generic graph, by CasADi's differentiation."""
    r, w = p.residual, p.w
    jr = ca.jacobian(r, w)
    f = 0.5 * ca.sumsqr(r)
    return ca.Function("ref", [w], [f, p.g, ca.gradient(f, w), ca.jacobian(p.g, w), ca.triu(ca.mtimes(jr.T, jr))])


@pytest.mark.parametrize("output_gain", [True, False])
@pytest.mark.parametrize("compile_mode", ["never", "always"])
@pytest.mark.parametrize("method", ["multiple_shooting", "single_shooting", "single_shooting_folded"])
def test_structured_callbacks_equal_casadi_derivatives_of_the_graph(monkeypatch, tmp_path, method, compile_mode,
                                                                     output_gain):
    """single_shooting: the MX graph of mapped blocks (a short record); _folded: the callbacks of
    single_pass, each one folded loop, that long records get."""
    from greyfit.solvers.methods.shooting import structured as structured_mod
    folded = method == "single_shooting_folded"
    monkeypatch.setattr(structured_mod, "FOLD_MIN_SAMPLES", 0 if folded else 10 ** 9)
    method = method.removesuffix("_folded")
    monkeypatch.setenv("GREYFIT_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv("GREYFIT_COMPILE", compile_mode)
    build = build_multiple_shooting if method == "multiple_shooting" else build_single_shooting
    structured = build(_oem(_body(method, output_gain)))
    assert structured.solver_factory is not None
    if method == "multiple_shooting":
        graph = structured.graph()
    else:
        monkeypatch.setenv("GREYFIT_STRUCTURED_SHOOTING", "0")
        graph = build(_oem(_body(method, output_gain)))
    ref = _reference(graph)
    solver = structured.solver_factory()
    nlp, data = solver.nlp.solver, solver.data
    # Ipopt's interface copies the gradient's nonzeros as they come: it must be dense
    assert nlp.get_function("nlp_grad_f").sparsity_out(1).is_dense()
    rng = np.random.default_rng(3)
    w0 = structured.initial_guess(np.array([0.5, 2.0, 1.0, 1.0, 1.2][:structured.n_theta]))
    for trial in range(3):
        w = w0 * (1 + 0.1 * rng.standard_normal(w0.size)) if trial else w0
        f, g, grad, jac, hess = (np.array(ca.DM(v)) for v in ref(w))
        lam = rng.standard_normal(g.size)
        ours = {
            "f": nlp.get_function("nlp_f")(w, data),
            "g": nlp.get_function("nlp_g")(w, data),
            "grad": nlp.get_function("nlp_grad_f")(w, data)[1],
            "jac": nlp.get_function("nlp_jac_g")(w, data)[1],
            "hess": nlp.get_function("nlp_hess_l")(w, data, 1.0, lam),
        }
        for name, truth in (("f", f), ("g", g), ("grad", grad), ("jac", jac), ("hess", hess)):
            got = np.array(ca.DM(ours[name]))
            assert got.shape == truth.shape, name
            scale = max(1.0, float(np.max(np.abs(truth)))) if truth.size else 1.0
            assert np.max(np.abs(got - truth), initial=0.0) <= 1e-9 * scale, name


def test_single_shooting_starts_its_barrier_small_and_reaches_the_same_optimum():
    """Ipopt's default first barrier weight (0.1 on its scaled objective) bent single shooting's first
    steps on a least-squares cost and took iterations to wind down: the README's mass-spring-damper
    (101 samples, both states measured) took 5, the seat model 11. Single shooting now starts the
    barrier at 1e-3 (4 iterations here); the optimum is multiple shooting's, which keeps the default."""
    import greyfit
    from tests.systems import msd_experiment, msd_model, simulate_msd

    t = np.linspace(0, 10, 101)
    exp = msd_experiment(t, simulate_msd(t), noise=0.005, seed=1)
    fits = {m: greyfit.fit(FitRequest.model_validate({"model": msd_model(c=0.5, k=3.0), "method": m,
                                                       "experiments": [exp]}))
            for m in ("single_shooting", "multiple_shooting")}
    ss, ms = fits["single_shooting"], fits["multiple_shooting"]
    assert ss.solver.return_status == "Solve_Succeeded" and ss.solver.iterations <= 4
    for name in ("c", "k"):
        assert ss.parameters[name].value == pytest.approx(ms.parameters[name].value, rel=1e-6)
