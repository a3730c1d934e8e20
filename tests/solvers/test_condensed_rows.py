"""The compiled loops behind every fit's checks: the condensed Jacobian (single_pass.condensed_rows)
and the lack-of-fit screen's sensitivity recursion (scoring_outputs.propagate).

Truth: central finite differences of the residual itself (independent of any Jacobian code), and
the interpreted forms that run until they are compiled (CasADi's interpreter; the Python recursion), on a
case with every complication the layout has: two records of different lengths, an initial state
estimated in one and known in the other, a missing sample, a per-experiment parameter.
"""
from collections import OrderedDict

import numpy as np
import pytest

from greyfit.schemas import FitRequest
from greyfit.solvers.data.experiments import prepare_experiments
from greyfit.solvers.dynamics import compiled as compiled_mod
from greyfit.solvers.methods.shooting import single_pass, structured
from greyfit.solvers.methods.shooting.model import OutputErrorModel
from greyfit.solvers.model import compiler as compiler_mod
from greyfit.solvers.model.compiler import compile_model
from greyfit.solvers.model.parameters import build_layout
from greyfit.solvers.screening import scoring_outputs
from tests.systems import msd_experiment, msd_model, simulate_msd

needs_cc = pytest.mark.skipif(compiled_mod.compiler() is None, reason="no C compiler on this machine")


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("GREYFIT_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(compiled_mod, "_memory", {})
    return tmp_path


def _oem():
    model = msd_model(c=0.4, k=3.0)
    model["parameters"][2]["per_experiment"] = True   # k: one value per record
    t1, t2 = np.arange(61) * 0.05, np.arange(47) * 0.05
    e1 = msd_experiment(t1, simulate_msd(t1), 0.01, 1, name="e1")
    e1["outputs"]["x"][7] = None
    e1["initial_state"] = {"v": 0.0}                 # x(0) estimated
    e2 = msd_experiment(t2, simulate_msd(t2), 0.01, 2, name="e2")
    e2["initial_state"] = {"x": 0.1, "v": 0.0}
    request = FitRequest.model_validate({"model": model, "method": "single_shooting", "experiments": [e1, e2]})
    cm = compile_model(request.model)
    data = prepare_experiments(request.experiments, cm)
    layout = build_layout(request.model, [d.name for d in data])
    return OutputErrorModel(cm, data, layout, request.options)


@needs_cc
def test_condensed_rows_are_the_residuals_derivatives(cache, monkeypatch):
    monkeypatch.setenv("GREYFIT_COMPILE", "always")
    oem = _oem()
    assert single_pass.row_columns(oem).ready()
    theta = np.array([0.9, 1.1, 0.95])               # scaled c, k@e1, k@e2: away from the optimum
    x0s = [{"x": 0.13, "v": 0.0}, {"x": 0.1, "v": 0.0}]
    jac, res, groups = single_pass.condensed_rows(oem, theta, x0s)
    assert jac.shape == (61 * 2 - 1 + 47 * 2, 4)     # one x sample missing; c, k@e1, k@e2, x0@e1
    assert set(groups) == {0, 1}

    def residual(w):
        x0 = [{"x": w[3] * oem.xscale[0], "v": 0.0}, x0s[1]]
        return single_pass.condensed_rows(oem, w[:3], x0)[1]
    w0 = np.concatenate([theta, [0.13 / oem.xscale[0]]])
    for j in range(4):
        h = 1e-6 * max(abs(w0[j]), 1.0)
        up, down = w0.copy(), w0.copy()
        up[j] += h
        down[j] -= h
        fd = (residual(up) - residual(down)) / (2 * h)
        assert np.allclose(jac[:, j], fd, rtol=1e-6, atol=1e-7 * np.abs(fd).max())
    # k@e1 moves only the first record's rows, k@e2 only the second's
    first = 61 * 2 - 1
    assert np.all(jac[first:, 1] == 0) and np.all(jac[:first, 2] == 0) and np.all(jac[first:, 3] == 0)

    monkeypatch.setenv("GREYFIT_COMPILE", "never")   # CasADi's interpreter, as before the library is built
    monkeypatch.setattr(compiled_mod, "_memory", {})
    monkeypatch.setattr(compiler_mod, "_COMPILED", OrderedDict())   # a new structure: nothing derived yet
    oem_interpreted = _oem()
    assert not single_pass.row_columns(oem_interpreted).ready()
    g_jac, g_res, g_groups = structured.condensed_jacobian(oem_interpreted, theta, x0s)
    assert np.allclose(g_jac, jac, rtol=1e-12, atol=1e-14)
    assert np.allclose(g_res, res, rtol=1e-12, atol=1e-14)
    assert np.array_equal(g_groups, groups)


@needs_cc
@pytest.mark.parametrize("how", ["always", "never"])
def test_the_solves_last_pass_holds_the_condensed_rows(cache, monkeypatch, how):
    """The single-shooting pass that gives Ipopt the gradient and JᵀJ also keeps r_k and J_k per
    sample, so J at the solve's optimum needs no pass of its own: the rows it keeps are those of the
    row kernel (compiled and interpreted), on the layout with every complication; asked at another
    point, they are not used."""
    monkeypatch.setenv("GREYFIT_COMPILE", how)
    oem = _oem()
    theta = np.array([0.9, 1.1, 0.95])
    w = np.concatenate([theta, [0.13 / oem.xscale[0]]])
    x0s = [{"x": w[3] * oem.xscale[0], "v": 0.0}, {"x": 0.1, "v": 0.0}]
    folds, _ = structured._single_folds(oem, sum(d.n for d in oem.data))
    sp = structured._single_pass(oem, folds)
    token, record = structured._token_record(oem)
    sp.attach(record)
    cost, grad, _ = sp.derivatives(w, np.array([token]))
    assert sp.rows_at(w + 1e-9, token) is None and sp.rows_at(w, token + 1.0) is None   # another point, record
    jac, res, groups = structured.condensed_jacobian(oem, theta, x0s, w)
    assert sp.rows_at(w, token) is None          # taken: a pass does not hold a record's rows after
    monkeypatch.setattr(single_pass, "_ROWS", OrderedDict())   # the row kernel's own pass
    want_jac, want_res, want_groups = single_pass.condensed_rows(oem, theta, x0s)
    assert jac.shape == want_jac.shape == (61 * 2 - 1 + 47 * 2, 4)
    assert np.allclose(jac, want_jac, rtol=1e-12, atol=1e-14 * np.abs(want_jac).max())
    assert np.allclose(res, want_res, rtol=1e-12, atol=1e-14 * np.abs(want_res).max())
    assert np.array_equal(groups, want_groups)
    assert np.isclose(cost, 0.5 * want_res @ want_res, rtol=1e-12)   # the same point's residual
    assert np.allclose(grad, want_jac.T @ want_res, rtol=1e-10, atol=1e-12 * np.abs(grad).max())
    monkeypatch.setattr(single_pass, "_ROWS", OrderedDict())
    elsewhere = structured.condensed_jacobian(oem, theta, x0s, w + 1e-3)   # not the pass's point: computed
    assert np.allclose(elsewhere[0], want_jac, rtol=1e-12, atol=1e-14 * np.abs(want_jac).max())


@needs_cc
@pytest.mark.parametrize("nx, w", [(2, 3), (3, 9), (1, 1)])
def test_compiled_recursion_equals_the_products_written_out(cache, monkeypatch, nx, w):
    monkeypatch.setenv("GREYFIT_COMPILE", "always")
    monkeypatch.setattr(scoring_outputs, "_RECURSIONS", {})
    rng = np.random.default_rng(nx * 10 + w)
    n, ny = 23, 2
    a, d0, d1 = (rng.standard_normal((n - 1, nx, nx)) * 0.5 for _ in range(3))
    hx, forcing = rng.standard_normal((n, ny, nx)), rng.standard_normal((n, nx, w))
    got = scoring_outputs.propagate(a, d0, d1, hx, forcing)
    assert scoring_outputs._recursion(nx, ny, w).ready()
    s = np.zeros((nx, w))
    want = [hx[0] @ s]
    for k in range(n - 1):   # S_{k+1} = A_k S_k + D0_k f_k + D1_k f_{k+1}
        s = a[k] @ s + d0[k] @ forcing[k] + d1[k] @ forcing[k + 1]
        want.append(hx[k + 1] @ s)
    assert np.allclose(got, np.array(want), rtol=1e-12, atol=1e-13)
    monkeypatch.setenv("GREYFIT_COMPILE", "never")   # the Python loop: the same numbers
    monkeypatch.setattr(scoring_outputs, "_RECURSIONS", {})
    assert np.allclose(scoring_outputs.propagate(a, d0, d1, hx, forcing), got, rtol=1e-12, atol=1e-13)


@needs_cc
@pytest.mark.parametrize("nx, ny, equations, picker", [
    (8, 8, [4] * 7 + [5] * 7 + [6] * 9 + [7] * 5, "identity"),   # the seat's screen: 4 equations, 28 columns
    (3, 2, [2, 0, 2], "rows"),                                     # outputs pick states 2 and 0
    (3, 2, [0, 2, 2, 1], None)])                                   # outputs mix the states
def test_recursion_by_equation_equals_the_products_written_out(cache, monkeypatch, nx, ny, equations, picker):
    """Columns that each force one equation take a drive of D_k[:, i] f_k, grouped by equation, and
    the outputs' product is skipped where H_k picks states: the same numbers as the dense recursion,
    in the order the columns were given, compiled or not."""
    monkeypatch.setenv("GREYFIT_COMPILE", "always")
    monkeypatch.setattr(scoring_outputs, "_RECURSIONS", {})
    rng = np.random.default_rng(nx * 100 + len(equations))
    n = 41
    a, d0, d1 = (rng.standard_normal((n - 1, nx, nx)) * 0.5 / np.sqrt(nx) for _ in range(3))   # stable
    if picker is None:
        hx = rng.standard_normal((n, ny, nx))
    else:
        h = np.eye(nx)[:ny] if picker == "identity" else np.eye(nx)[[2, 0]]
        hx = np.repeat(h[None], n, axis=0)
    columns = [(i, rng.standard_normal(n)) for i in equations]
    s = np.zeros((nx, len(columns)))
    forcing = np.zeros((n, nx, len(columns)))
    for c, (i, values) in enumerate(columns):
        forcing[:, i, c] = values
    want = [hx[0] @ s]
    for k in range(n - 1):
        s = a[k] @ s + d0[k] @ forcing[k] + d1[k] @ forcing[k + 1]
        want.append(hx[k + 1] @ s)
    got = scoring_outputs.propagate_by_equation(a, d0, d1, hx, columns)
    groups = len({(i, k // scoring_outputs.PROPAGATE_COLUMNS) for i in set(equations)
                  for k in range(equations.count(i))})
    assert scoring_outputs._recursion_by_equation(nx, 0 if picker else ny, groups).ready()
    assert np.allclose(got, np.array(want), rtol=1e-12, atol=1e-13)
    start = rng.standard_normal(got.shape)   # `into`: added to what is there
    assert np.allclose(scoring_outputs.propagate_by_equation(a, d0, d1, hx, columns, into=start.copy()),
                       start + got, rtol=1e-12, atol=1e-13)
    monkeypatch.setenv("GREYFIT_COMPILE", "never")   # the Python loop: the same numbers
    monkeypatch.setattr(scoring_outputs, "_RECURSIONS", {})
    assert np.allclose(scoring_outputs.propagate_by_equation(a, d0, d1, hx, columns), got, rtol=1e-12, atol=1e-13)


@needs_cc
def test_a_fit_prepares_its_records_once_and_its_checks_reuse_the_optimums_jacobian(cache, monkeypatch):
    """The solve, the step choice, the input reading and the lack-of-fit screen each prepared the
    request's records (a 200 000-sample series converted from its list four times), and each
    condensed Jacobian was keyed by a digest of the records (7 ms at 200 000 samples). Now a fit
    prepares once, and the screen finds the solve's Jacobian at the optimum by the records' identity:
    the rows at the optimum are the solve's last pass's (the start checks' JᵀJ is its first pass),
    so the rows kernel never runs, and the input reading and the screen reuse them (the input
    reading's finer records are simulated)."""
    from greyfit.solvers.data import experiments as experiments_mod
    from greyfit.solvers.fit import fit_model

    monkeypatch.setenv("GREYFIT_COMPILE", "always")
    prepared, rows_runs, kernels = [], [], {}
    real_prepare, real_rows = experiments_mod.prepare_experiment, single_pass.row_columns
    monkeypatch.setattr(experiments_mod, "prepare_experiment",
                        lambda exp, cm, i: prepared.append(exp.name) or real_prepare(exp, cm, i))

    class Counting:
        def __init__(self, kernel):
            self.kernel = kernel

        def ready(self):
            return self.kernel.ready()

        def __call__(self, *args, n, **kw):
            rows_runs.append(n)
            return self.kernel(*args, n=n, **kw)

    def rows(oem):   # one proxy per kernel: condensed_rows's cache holds its kernel by identity
        kernel = real_rows(oem)
        return kernels.setdefault(id(kernel), (kernel, Counting(kernel)))[1]
    monkeypatch.setattr(single_pass, "row_columns", rows)
    t = np.linspace(0.0, 10.0, 401)
    request = FitRequest.model_validate({"model": msd_model(), "method": "single_shooting",
                                         "experiments": [msd_experiment(t, simulate_msd(t), 0.005, 3)]})
    result = fit_model(request)
    assert result.solver.return_status == "Solve_Succeeded"
    assert abs(result.parameters["c"].value - 0.8) < 0.05 and abs(result.parameters["k"].value - 5.0) < 0.1
    assert prepared == ["e1"]
    assert rows_runs == []                             # the solve's last pass wrote them
    arrays = experiments_mod.prepare_experiments(request.experiments, compile_model(request.model))[0]
    with pytest.raises(ValueError):                   # shared, so never changed in place
        arrays.y[0, 0] = 1.0


def test_the_input_readings_simulated_residual_is_the_rows_residual(cache):
    """The input reading takes the ramps' residual from a simulation instead of a sensitivity pass:
    the same rows (a missing sample, two records, per-record parameters), to rounding."""
    from greyfit.solvers.checks.input_reading import _weighted_residual

    oem = _oem()
    theta = np.array([0.9, 1.1, 0.95])
    x0s = [{"x": 0.13, "v": 0.0}, {"x": 0.1, "v": 0.0}]
    _, res, _ = single_pass.condensed_rows(oem, theta, x0s)
    simulated = _weighted_residual(oem, theta, x0s)
    assert simulated.shape == res.shape == (61 * 2 - 1 + 47 * 2,)
    assert np.allclose(simulated, res, rtol=0, atol=1e-12 * np.abs(res).max())
    assert np.abs(res).max() > 0.1                     # away from the optimum: a real residual


def test_the_input_readings_two_readings_are_the_residuals_of_the_finer_records(cache):
    """The input reading simulates both readings on the finer grid but reads the outputs at the
    measured samples only: the same rows as the residual of the finer records themselves (outputs
    missing between the samples), two records, a missing sample, per-record parameters."""
    from greyfit.solvers.checks.input_reading import _weighted_residual, _weighted_residuals_on_finer_grid
    from greyfit.solvers.data.experiments import ExperimentData
    from greyfit.solvers.data.refine import cubic_on_finer_grid, linear_on_finer_grid

    oem = _oem()
    theta = np.array([0.9, 1.1, 0.95])
    x0s = [{"x": 0.13, "v": 0.0}, {"x": 0.1, "v": 0.0}]
    fine = oem.options.model_copy(update={"substeps": 1})
    cubic, linear = _weighted_residuals_on_finer_grid(oem, OutputErrorModel(oem.cm, oem.data, oem.layout, fine),
                                                       theta, x0s, 4)
    for reading, got in ((lambda d: cubic_on_finer_grid(d.t, d.u, 4)[1], cubic),
                         (lambda d: linear_on_finer_grid(d.t, d.u, 4), linear)):
        records = []
        for d in oem.data:
            t, _ = cubic_on_finer_grid(d.t, d.u, 4)
            y = np.full((d.y.shape[0], t.size), np.nan)
            y[:, ::4] = d.y
            records.append(ExperimentData(d.name, t, reading(d), y, d.x0_known, {}))
        finer = OutputErrorModel(oem.cm, records, oem.layout, fine)
        finer.weights = oem.weights
        expected = _weighted_residual(finer, theta, x0s)
        assert got.shape == expected.shape == (61 * 2 - 1 + 47 * 2,)
        assert np.allclose(got, expected, rtol=0, atol=1e-13 * np.abs(expected).max())
    assert np.abs(cubic - linear).max() > 0                # the readings differ between the samples


def test_a_simulation_asked_again_is_the_same_and_a_copy(cache, monkeypatch):
    """The optimum is simulated by the residual channels, the screen and its scorer: the second ask
    of a record, x0 and parameters is served from the last simulations (a copy: changing it changes
    nothing kept), and another point is simulated anew (its own numbers)."""
    from greyfit.solvers.methods.shooting import model as model_mod

    oem = _oem()
    x0 = np.array([0.13, 0.0])
    p = np.asarray(oem.layout.full(0, np.array([0.9, 1.1, 0.95])), dtype=float).ravel()
    runs = []
    real = oem.step_inputs
    monkeypatch.setattr(oem, "step_inputs", lambda *a: runs.append(1) or real(*a))
    first = oem.numeric_states(0, x0, p)
    first[:, :] = np.nan
    second = oem.numeric_states(0, x0, p)
    assert len(runs) == 1                                  # the second ask did not simulate
    assert np.all(np.isfinite(second)) and second.shape == (2, 61)
    model_mod._STATES.clear()
    assert np.array_equal(oem.numeric_states(0, x0, p), second)   # simulated anew: the same numbers
    other = oem.numeric_states(0, x0, p * 1.1)
    assert not np.allclose(other, second)


def test_a_retrys_cpu_budget_keeps_the_structures_solver():
    """Ipopt's CPU limit is fixed when its instance is made: a retry's budget (the fit's CPU time
    left) is floored to a grid so that budgets a few milliseconds apart share one instance, never
    above what was asked."""
    for asked in (120.0, 119.97, 60.0, 20.0, 1.0, 0.05, 1e-4):
        got = structured.ipopt_cpu_limit(asked)
        assert asked / 2 ** (1 / structured.CPU_LIMIT_STEPS_PER_OCTAVE) < got <= asked
    assert structured.ipopt_cpu_limit(120.0) == structured.ipopt_cpu_limit(119.97)
    assert structured.ipopt_cpu_limit(1.0) == 1.0
