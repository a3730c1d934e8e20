"""Single shooting's folded callbacks (solvers/methods/shooting/single_pass.py, columns.Fold).

Truth: CasADi's own `mapaccum` of the same Function (the fold), a fit by the interpreted kernels
(the compiled one must reach the same optimum), and the simulated record's known parameters. The
count test guards the point of the design: one sensitivity pass per accepted point, shared by the
gradient and the Hessian callbacks.
"""
import numpy as np
import pytest

from greyfit.schemas import FitRequest
from greyfit.solvers.dynamics import compiled as compiled_mod
from greyfit.solvers.dynamics.columns import Fold
from greyfit.solvers.fit import fit_model
from greyfit.solvers.methods.shooting import single_pass
from tests.systems import MSD_TRUTH, msd_experiment, msd_model, simulate_msd

needs_cc = pytest.mark.skipif(compiled_mod.compiler() is None, reason="no C compiler on this machine")


@pytest.fixture
def cache(tmp_path, monkeypatch):
    from greyfit.solvers.methods.shooting import structured
    monkeypatch.setattr(structured, "FOLD_MIN_SAMPLES", 0)   # the folded callbacks at every length
    monkeypatch.setenv("GREYFIT_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(compiled_mod, "_memory", {})
    return tmp_path / "compiled"


def _request(n=501, seed=2):
    t = np.arange(n) * 0.02
    model = msd_model(c=0.4, k=3.0)
    model["outputs"] = {"x": "x"}
    return FitRequest.model_validate({"model": model, "method": "single_shooting", "experiments": [
        msd_experiment(t, simulate_msd(t), 0.002, seed, outputs=("x",))]})


@needs_cc
def test_fold_in_c_equals_casadis_mapaccum_summed(cache, monkeypatch):
    """The compiled fold: the state after the last sample and the other outputs summed, with a
    per-sample and a shared input, a sparse and a dense output, a record of no special length."""
    import casadi as ca
    monkeypatch.setenv("GREYFIT_COMPILE", "always")
    x, p, u = ca.SX.sym("x", 3), ca.SX.sym("p", 2), ca.SX.sym("u")
    xn = ca.vertcat(0.9 * x[0] + p[0] * u, x[1] * 0.5 + ca.sin(x[2]), 0.8 * x[2] - p[1] * u)
    fn = ca.Function("fold_case", [x, p, u], [xn, ca.sumsqr(x - u), ca.triu(ca.mtimes(x, x.T)), p * x[0]])
    rng = np.random.default_rng(1)
    n, x0, pv = 333, np.array([0.3, -0.2, 1.0]), np.array([0.7, 0.2])
    us = rng.standard_normal(n)
    fold = Fold(fn, 1e9)
    assert fold.compiled
    got = fold(x0, pv, us, n=n)
    acc = fn.mapaccum(n)(x0, pv, us.reshape(1, n))
    want = [np.array(acc[0][:, -1]).ravel()] + [np.array(ca.sum2(acc[j])).ravel() for j in (1, 3)]
    assert np.allclose(got[0], want[0], rtol=1e-13, atol=0)
    assert np.allclose(got[1], want[1], rtol=1e-12, atol=0)
    assert np.allclose(got[3], want[2], rtol=1e-12, atol=0)
    # the sparse triu output: its nonzeros summed
    triu = sum(np.triu(np.outer(s, s)) for s in np.hstack([x0[:, None], np.array(acc[0])[:, :-1]]).T)
    rows, cols = fn.sparsity_out(2).get_triplet()
    assert np.allclose(got[2], triu[rows, cols], rtol=1e-12, atol=0)
    monkeypatch.setenv("GREYFIT_COMPILE", "never")   # the interpreted fallback: the same numbers
    plain = Fold(fn)
    assert not plain.compiled
    for g, w in zip(plain(x0, pv, us, n=n), got):
        assert np.allclose(g, w, rtol=1e-12, atol=1e-15)


@needs_cc
def test_compiled_and_interpreted_folds_reach_the_same_optimum(cache, monkeypatch):
    monkeypatch.setenv("GREYFIT_COMPILE", "never")
    plain = fit_model(_request())
    monkeypatch.setenv("GREYFIT_COMPILE", "always")
    fast = fit_model(_request())
    assert plain.solver.compiled is False and fast.solver.compiled is True
    for name in ("c", "k"):
        assert fast.parameters[name].value == pytest.approx(plain.parameters[name].value, rel=1e-9)
        assert fast.parameters[name].value == pytest.approx(MSD_TRUTH[name], rel=5e-3)
    assert fast.metrics.cost == pytest.approx(plain.metrics.cost, rel=1e-10)


@pytest.mark.parametrize("mode", ["never", "always"])
def test_one_sensitivity_pass_per_accepted_point(cache, monkeypatch, mode):
    """grad_f and hess_l at the same point share one sensitivity pass: over a fit, no more passes
    than Ipopt's iterations plus the start (each iteration accepts one point). The start checks'
    JᵀJ at the guess is that start's pass (`start_gram`), not one more."""
    if mode == "always" and compiled_mod.compiler() is None:
        pytest.skip("no C compiler on this machine")
    monkeypatch.setenv("GREYFIT_COMPILE", mode)
    passes = []
    original = single_pass.SinglePass.derivatives

    def counted(self, w, p):
        before = self._point
        out = original(self, w, p)
        if self._point is not before:   # computed, not read from the point's cache
            passes.append(1)
        return out

    monkeypatch.setattr(single_pass.SinglePass, "derivatives", counted)
    result = fit_model(_request(n=301, seed=4))
    assert result.quality == "good"
    assert result.parameters["k"].value == pytest.approx(MSD_TRUTH["k"], rel=5e-3)
    assert 0 < len(passes) <= result.solver.iterations + 1


@pytest.mark.parametrize("mode", ["never", "always"])
def test_callbacks_equal_the_graphs_derivatives_when_some_initial_states_are_known(cache, monkeypatch, mode):
    """v(0) known in both experiments: the kernels carry no v(0) direction, and the Gauss-Newton
    pieces still equal CasADi's differentiation of the generic single-shooting graph."""
    import casadi as ca

    from greyfit.solvers.methods.shooting import build_single_shooting
    from tests.solvers.test_structured_nlp import _body, _oem, _reference
    if mode == "always" and compiled_mod.compiler() is None:
        pytest.skip("no C compiler on this machine")
    monkeypatch.setenv("GREYFIT_COMPILE", mode)
    body = _body("single_shooting", output_gain=True)
    body["experiments"][0]["initial_state"] = {"v": -0.1}
    structured = build_single_shooting(_oem(body))
    assert single_pass.free_states(_oem(body)) == (0,)
    monkeypatch.setenv("GREYFIT_STRUCTURED_SHOOTING", "0")
    ref = _reference(build_single_shooting(_oem(body)))
    monkeypatch.delenv("GREYFIT_STRUCTURED_SHOOTING")
    solver = structured.solver_factory()
    nlp, data = solver.nlp.solver, solver.data
    w = structured.initial_guess(np.array([0.5, 2.0, 1.0, 1.0, 1.2])) * 1.05
    f, _, grad, _, hess = (np.array(ca.DM(v)) for v in ref(w))
    got = {"f": nlp.get_function("nlp_f")(w, data), "grad": nlp.get_function("nlp_grad_f")(w, data)[1],
           "hess": nlp.get_function("nlp_hess_l")(w, data, 1.0, np.zeros(nlp.size1_in(5)))}
    for name, truth in (("f", f), ("grad", grad), ("hess", hess)):
        value = np.array(ca.DM(got[name]))
        assert value.shape == truth.shape, name
        assert np.max(np.abs(value - truth)) <= 1e-9 * max(1.0, float(np.max(np.abs(truth)))), name


@needs_cc
def test_the_start_checks_gram_is_the_condensed_jacobians(cache, monkeypatch):
    """`start_gram` (JᵀJ at the guess from the solve's own sensitivity pass) equals JᵀJ of the
    condensed Jacobian that the start checks computed before, with a free initial state."""
    from greyfit.solvers.methods.shooting import build_single_shooting
    from greyfit.solvers.methods.shooting.model import sensitivity_jacobian
    from tests.solvers.test_structured_nlp import _body, _oem
    monkeypatch.setenv("GREYFIT_COMPILE", "always")
    body = _body("single_shooting", output_gain=True)
    oem = _oem(body)
    problem = build_single_shooting(oem)
    assert problem.start_gram is not None
    w = problem.initial_guess(oem.layout.initial) * 1.03
    gram = problem.start_gram(w)
    theta_s = w[:oem.layout.size]
    x0s = problem.x0_of(w)
    jac, _, _ = sensitivity_jacobian(oem, theta_s, x0s)
    assert gram.shape == (jac.shape[1],) * 2
    assert np.allclose(gram, jac.T @ jac, rtol=1e-10, atol=1e-12 * np.abs(gram).max())


@needs_cc
def test_fits_of_one_structure_in_threads_each_get_their_own_record(cache, monkeypatch):
    """The records reach the shared callbacks by token, not through Ipopt: four fits of one model
    structure running at once in threads (CasADi releases the GIL) each answer for their own data,
    exactly as one at a time."""
    from concurrent.futures import ThreadPoolExecutor
    monkeypatch.setenv("GREYFIT_COMPILE", "always")
    requests = [_request(seed=s) for s in (11, 12, 13, 14)]
    alone = [fit_model(r) for r in requests]
    with ThreadPoolExecutor(max_workers=4) as pool:
        together = list(pool.map(fit_model, requests))
    for a, b in zip(alone, together):
        assert b.solver.compiled is True
        for name in ("c", "k"):
            assert b.parameters[name].value == a.parameters[name].value
    assert len({round(r.parameters["k"].value, 12) for r in alone}) == 4   # four different records
