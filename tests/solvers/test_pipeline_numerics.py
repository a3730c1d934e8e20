"""The checks around the solve, computed the fast way, against the direct computation they replace.

The pipeline runs the lack-of-fit screen's step Jacobians, the substep choice's and the
errors-in-variables check's simulations as compiled sample loops, and its Newey-West sums from
cumulative sums; each is pinned here to the plain CasADi graph or the formula written out, and a
fit's residual analysis to the direct sums over its own residual trace.
"""
import casadi as ca
import numpy as np
import pytest

from greyfit.schemas import FitRequest
from greyfit.solvers.checks.simulation import numeric_step
from greyfit.solvers.data.experiments import prepare_experiments
from greyfit.solvers.dynamics.integration import make_step
from greyfit.solvers.fit import fit_model
from greyfit.solvers.methods.equation_error_bias import _hac
from greyfit.solvers.methods.shooting import OutputErrorModel
from greyfit.solvers.model.compiler import compile_model
from greyfit.solvers.model.parameters import build_layout
from tests.systems import msd_experiment, msd_model, simulate_msd

T = np.linspace(0, 10, 201)


def _request(method: str, interpolation: str = "foh") -> FitRequest:
    return FitRequest.model_validate({
        "model": msd_model(c=0.5, k=3.0), "method": method,
        "experiments": [msd_experiment(T, simulate_msd(T), noise=0.005, seed=1)],
        "options": {"return_traces": True, "input_interpolation": interpolation}})


@pytest.mark.parametrize("method", ["multiple_shooting", "equation_error"])
def test_residual_analysis_matches_the_direct_sums_over_the_residual_trace(method):
    result = fit_model(_request(method))
    trace = result.traces[0]
    for a in result.residual_analysis:
        r = np.array([np.nan if v is None else v for v in trace.residuals[a.output]])
        y = np.array(trace.simulated[a.output], dtype=float) - r   # null where the row is not used
        ok = np.isfinite(r)
        r, y = r[ok], y[ok]
        assert a.rmse == pytest.approx(np.sqrt(np.mean(r ** 2)), rel=1e-10)
        spread = np.sqrt(np.sum((y - y.mean()) ** 2))
        assert a.fit_percent == pytest.approx(100 * (1 - np.sqrt(np.sum(r ** 2)) / spread), rel=1e-10)
        e = r - r.mean()
        direct = [np.sum(e[k:] * e[:e.size - k]) / np.sum(e * e) for k in range(len(a.autocorrelation))]
        np.testing.assert_allclose(a.autocorrelation, direct, rtol=0, atol=1e-12)
        assert a.whiteness.max_abs == pytest.approx(np.max(np.abs(direct[1:])), rel=1e-10)


@pytest.mark.parametrize("interpolation", ["foh", "zoh"])
def test_disturbed_step_jacobians_match_the_casadi_graph(interpolation):
    """The screen's ∂x+/∂x, ∂x+/∂d0, ∂x+/∂d1 at d = 0 (compiled loop; a disturbance d on ẋ, held or
    linear like the inputs) = the MX Jacobians of the disturbed step in [u; d] evaluated by map,
    their disturbance columns."""
    from types import SimpleNamespace

    from greyfit.solvers.screening.scoring_outputs import _disturbed_step
    request = _request("single_shooting", interpolation)
    cm = compile_model(request.model)
    data = prepare_experiments(request.experiments, cm)
    oem = OutputErrorModel(cm, data, build_layout(request.model, [d.name for d in data]), request.options)
    d, n = data[0], data[0].n - 1
    rng = np.random.default_rng(3)
    x = rng.standard_normal((cm.nx, n))
    u0, u1, t0, dt = oem.step_inputs(d, 0, n)
    p = np.array([2.0, 0.5, 3.0])
    got = _disturbed_step(oem)(x, u0, u1, p, t0, dt, n=n)
    # the graph the screen used to evaluate: the disturbed RK4 step in MX, differentiated by CasADi
    xs, us, ds = ca.SX.sym("x", cm.nx), ca.SX.sym("u", cm.nu), ca.SX.sym("d", cm.nx)
    ps, ts = ca.SX.sym("p", cm.np), ca.SX.sym("t")
    rhs = ca.Function("rhs_d", [xs, ca.vertcat(us, ds), ps, ts], [cm.rhs(xs, us, ps, ts) + ds])
    step = make_step(SimpleNamespace(rhs=rhs, nx=cm.nx, nu=cm.nu + cm.nx, np=cm.np, model=cm.model), request.options)
    xm, a0, a1 = ca.MX.sym("x", cm.nx), ca.MX.sym("u0", cm.nu + cm.nx), ca.MX.sym("u1", cm.nu + cm.nx)
    pm, t0m, dtm = ca.MX.sym("p", cm.np), ca.MX.sym("t0"), ca.MX.sym("dt")
    xn = step(xm, a0, a1, pm, t0m, dtm)
    graph = ca.Function("g", [xm, a0, a1, pm, t0m, dtm], [ca.jacobian(xn, v) for v in (xm, a0, a1)])
    zero = np.zeros((cm.nx, n))
    a, j0, j1 = (np.array(e) for e in graph.map(n)(x, np.vstack([u0, zero]), np.vstack([u1, zero]),
                                                   np.repeat(p[:, None], n, 1), t0, dt))
    nud = cm.nu + cm.nx
    expected = [a] + [np.hstack([j[:, k * nud + cm.nu:(k + 1) * nud] for k in range(n)]) for j in (j0, j1)]
    for g, e in zip(got, expected):
        assert g.shape == e.shape == (cm.nx, n * cm.nx)
        np.testing.assert_allclose(g, e, rtol=1e-12, atol=1e-14)


def test_numeric_step_simulates_as_the_mapped_step():
    request = _request("single_shooting")
    cm = compile_model(request.model)
    d = prepare_experiments(request.experiments, cm)[0]
    n, p, x0 = d.n - 1, np.array([2.0, 0.5, 3.0]), np.array([0.1, 0.0])
    args = (d.u[:, :-1], d.u[:, 1:], p, d.t[None, :-1], np.diff(d.t)[None, :])
    got, = numeric_step(cm, request.options, n)(x0, *args, n=n, accumulate=True)
    expected = np.array(make_step(cm, request.options).mapaccum(n)(x0, *args))
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-15)
    assert numeric_step(cm, request.options) is numeric_step(cm, request.options)   # built once


@pytest.mark.parametrize("n,lags,cols", [(2000, 13, 2), (400, 52, 8), (30, 40, 2)])
def test_errors_in_variables_hac_equals_the_lag_by_lag_sum(n, lags, cols):
    m = np.random.default_rng(n).standard_normal((n, cols)) + 0.3   # an offset: cumulative sums grow
    expected = m.T @ m
    for lag in range(1, lags + 1):
        g = m[lag:].T @ m[:-lag]
        expected = expected + (1 - lag / (lags + 1)) * (g + g.T)
    np.testing.assert_allclose(_hac(m, lags), expected, rtol=0, atol=1e-11 * np.abs(expected).max())
