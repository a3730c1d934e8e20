"""The interpreter's chunked loops over long records (solvers/dynamics/columns.py, FOLD_CHUNK).

Truth: CasADi's own `map` and `mapaccum` over the whole record. Chunks bound what the interpreter
builds (a mapaccum of n samples costs time and memory in proportion to n to build: 1.5 s and 330 MB
at 200 000 samples); the numbers must not change where one chunk ends and the next begins: the
state carried across, a shared input repeated in every chunk, a sparse output, a remainder.
"""
import casadi as ca
import numpy as np
import pytest

from greyfit.solvers.dynamics import columns
from greyfit.solvers.dynamics.columns import Columns, Fold


@pytest.fixture
def interpreted(monkeypatch):
    monkeypatch.setenv("GREYFIT_COMPILE", "never")
    monkeypatch.setattr(columns, "FOLD_CHUNK", 7)   # 50 samples: 7 chunks and a remainder of 1


def _step():
    x, p, u = ca.SX.sym("x", 3), ca.SX.sym("p", 2), ca.SX.sym("u")
    xn = ca.vertcat(0.9 * x[0] + p[0] * u, x[1] * 0.5 + ca.sin(x[2]), 0.8 * x[2] - p[1] * u)
    return x, p, u, xn


def test_chunked_map_equals_the_whole_map(interpreted):
    x, p, u, xn = _step()
    fn = ca.Function("cols", [x, p, u], [xn, ca.jacobian(xn, x), ca.jacobian(xn, p)])   # sparse Jacobians
    rng = np.random.default_rng(0)
    n = 50
    xs, us, pv = rng.standard_normal((3, n)), rng.standard_normal((1, n)), np.array([1.5, -0.3])
    cols = Columns(fn)
    assert not cols.compiled
    got = cols(xs, pv, us, n=n)
    want = [o.full() for o in fn.map(n)(xs, pv[:, None], us)]
    for g, w in zip(got, want):
        assert g.shape == w.shape and np.array_equal(g, w)


def test_chunked_mapaccum_carries_the_state_across_chunks(interpreted):
    x, p, u, xn = _step()
    fn = ca.Function("acc", [x, p, u], [xn, x[0] * u])
    rng = np.random.default_rng(1)
    n, x0, pv = 50, np.array([0.3, -0.2, 1.0]), np.array([0.7, 0.2])
    us = rng.standard_normal((1, n))
    got = Columns(fn)(x0, pv, us, n=n, accumulate=True)
    want = [o.full() for o in fn.mapaccum(n)(x0, pv[:, None], us)]
    for g, w in zip(got, want):
        assert g.shape == w.shape
        assert np.allclose(g, w, rtol=1e-14, atol=0)


def test_chunked_fold_sums_across_chunks(interpreted, monkeypatch):
    x, p, u, xn = _step()
    fn = ca.Function("fold", [x, p, u], [xn, ca.sumsqr(x - u), ca.triu(ca.mtimes(x, x.T)), p * x[0]])
    rng = np.random.default_rng(2)
    n, x0, pv = 50, np.array([0.3, -0.2, 1.0]), np.array([0.7, 0.2])
    us = rng.standard_normal(n)
    fold = Fold(fn)
    assert not fold.compiled
    got = fold(x0, pv, us, n=n)
    acc = fn.mapaccum(n)(x0, pv, us.reshape(1, n))
    assert np.allclose(got[0], np.array(acc[0][:, -1]).ravel(), rtol=1e-14, atol=0)
    for j in (1, 3):
        assert np.allclose(got[j], np.array(ca.sum2(acc[j])).ravel(), rtol=1e-13, atol=0)
    monkeypatch.setattr(columns, "FOLD_CHUNK", n)   # one mapaccum of the whole record
    whole = Fold(fn)(x0, pv, us, n=n)
    # to the last bit, the sparse triu too: the sums are added sample after sample in both (the
    # compiled loop's order, which the handover from interpreted to compiled code relies on)
    assert all(np.array_equal(g, w) for g, w in zip(got, whole))
    bound = fold.bind([x0, pv, us], n)   # the path every single-shooting callback takes
    assert all(np.allclose(b, g, rtol=1e-15, atol=0) for b, g in zip(bound(), got))


def test_a_sparse_next_state_is_carried_into_the_dense_one(interpreted, monkeypatch):
    """A sensitivity that is structurally zero makes the step's next state sparse (a difference
    equation's delay states: 17 of 24 entries) while its input is dense: across a chunk boundary the
    nonzeros go back to their places, as CasADi's own mapaccum does."""
    x, p, u = ca.SX.sym("x", 3), ca.SX.sym("p", 2), ca.SX.sym("u")
    xn = ca.vertcat(0.9 * x[0] + p[0] * u, ca.SX(1, 1), 0.5 * x[2] + x[0] * x[1] + p[1])   # x[1]+ ≡ 0
    fn = ca.Function("sparse_step", [x, p, u], [xn, ca.sumsqr(x - u), p * x[2]])
    assert fn.sparsity_out(0).nnz() == 2 and fn.sparsity_in(0).nnz() == 3
    rng = np.random.default_rng(3)
    n, x0, pv = 50, np.array([0.3, -0.2, 1.0]), np.array([0.7, 0.2])
    us = rng.standard_normal(n)
    chunked = Fold(fn)(x0, pv, us, n=n)
    steps = Columns(fn)(x0, pv, us.reshape(1, n), n=n, accumulate=True)
    monkeypatch.setattr(columns, "FOLD_CHUNK", n)   # one mapaccum of the whole record
    assert all(np.array_equal(g, w) for g, w in zip(chunked, Fold(fn)(x0, pv, us, n=n)))
    whole = Columns(fn)(x0, pv, us.reshape(1, n), n=n, accumulate=True)
    assert all(np.array_equal(g, w) for g, w in zip(steps, whole))


@pytest.mark.skipif(__import__("greyfit.solvers.dynamics.compiled", fromlist=["compiler"]).compiler() is None,
                    reason="no C compiler on this machine")
def test_a_sparse_next_state_is_never_carried_by_the_compiled_loop(tmp_path, monkeypatch):
    """The compiled loops carry output 0 into input 0 as it stands: for a step whose next state is
    sparser than its state they read it from the wrong places (NaN here), so such a step is folded
    and accumulated by the interpreter, with CasADi's own numbers."""
    monkeypatch.setenv("GREYFIT_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv("GREYFIT_COMPILE", "always")
    x, p, u = ca.SX.sym("x", 3), ca.SX.sym("p", 2), ca.SX.sym("u")
    xn = ca.vertcat(0.9 * x[0] + p[0] * u, ca.SX(1, 1), 0.5 * x[2] + x[0] * x[1] + p[1])
    fn = ca.Function("sparse_step_c", [x, p, u], [xn, ca.sumsqr(x - u), p * x[2]])
    rng = np.random.default_rng(4)
    n, x0, pv = 40, np.array([0.3, -0.2, 1.0]), np.array([0.7, 0.2])
    us = rng.standard_normal(n)
    fold = Fold(fn, 1e9)
    assert not fold.compiled
    got = fold(x0, pv, us, n=n)
    acc = fn.mapaccum(n)(x0, pv, us.reshape(1, n))
    assert np.allclose(got[0], np.array(acc[0][:, -1]).ravel()[[0, 2]], rtol=1e-14, atol=0)
    assert np.allclose(got[1], float(ca.sum2(acc[1])), rtol=1e-13, atol=0)
    steps = Columns(fn)(x0, pv, us.reshape(1, n), n=n, accumulate=True)[0]
    assert np.allclose(steps, np.array(acc[0]), rtol=1e-14, atol=0)


@pytest.mark.parametrize("how", ["never", "always"])
def test_a_fold_keeps_its_per_sample_outputs(tmp_path, monkeypatch, how):
    """Outputs named per sample are kept at every sample, not summed, beside the sums (single
    shooting keeps each sample's residual and Jacobian row this way): the same numbers from the
    interpreter across chunk boundaries and from the compiled loop, as CasADi's own mapaccum."""
    from greyfit.solvers.dynamics import compiled as compiled_mod
    if how == "always" and compiled_mod.compiler() is None:
        pytest.skip("no C compiler on this machine")
    monkeypatch.setenv("GREYFIT_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv("GREYFIT_COMPILE", how)
    monkeypatch.setattr(columns, "FOLD_CHUNK", 16)   # several chunks in the interpreter
    x, p, u, xn = _step()
    fn = ca.Function(f"fold_rows_{how}", [x, p, u], [xn, ca.sumsqr(x - u), ca.vertcat(x[0] * u, x[2]),
                                                   ca.densify(ca.mtimes(x, p.T))])
    rng = np.random.default_rng(5)
    n, x0, pv = 50, np.array([0.3, -0.2, 1.0]), np.array([0.7, 0.2])
    us = rng.standard_normal(n)
    fold = Fold(fn, 1e9 if how == "always" else 0.0, per_sample=(2, 3))
    assert fold.compiled == (how == "always")
    got = fold.bind([x0, pv, us], n)()
    acc = fn.mapaccum(n)(x0, pv, us.reshape(1, n))
    assert np.allclose(got[0], np.array(acc[0][:, -1]).ravel(), rtol=1e-14, atol=0)
    assert np.allclose(got[1], float(ca.sum2(acc[1])), rtol=1e-13, atol=0)
    assert got[2].shape == (2 * n,) and got[3].shape == (6 * n,)
    # sample k's nonzeros at k·nnz .. (k+1)·nnz − 1, each block column-major
    assert np.allclose(got[2].reshape(n, 2).T, np.array(acc[2]), rtol=1e-14, atol=0)
    assert np.allclose(got[3].reshape(n, 2, 3).transpose(2, 0, 1).reshape(3, 2 * n), np.array(acc[3]),
                       rtol=1e-14, atol=0)
    with pytest.raises(ValueError):
        Fold(fn, per_sample=(0,))   # the carried state is never per sample
