"""ARMAX template fitted by prediction error (output error on the one-step predictor).

Truth: A = 1 − 1.5 q⁻¹ + 0.7 q⁻², B = q⁻¹ + 0.5 q⁻², C = 1 − q⁻¹ + 0.2 q⁻² (the classical
Åström–Ljung example), ±1 random binary input, white e of unit variance, simulated with scipy.
"""
import numpy as np
import pytest
from scipy import signal

from greyfit.schemas import FitRequest
from greyfit.schemas.model import Model
from greyfit.solvers.errors import DataError
from greyfit.solvers.fit import fit_model
from greyfit.solvers.model.compiler import compile_model

A, B, C = [1.0, -1.5, 0.7], [0.0, 1.0, 0.5], [1.0, -1.0, 0.2]
TRUTH = {"a1": -1.5, "a2": 0.7, "b1": 1.0, "b2": 0.5, "c1": -1.0, "c2": 0.2}


def armax_data(seed: int, n: int = 800):
    rng = np.random.default_rng(seed)
    u = rng.choice([-1.0, 1.0], n)
    e = rng.standard_normal(n)
    return np.arange(n, dtype=float), u, signal.lfilter(B, A, u) + signal.lfilter(C, A, e)


def request(t, u, y, kind: str, method: str, **options) -> FitRequest:
    template = {"kind": kind, "na": 2, "nb": 2, "nk": 1, **({"nc": 2} if kind == "armax" else {})}
    return FitRequest.model_validate({
        "model": {"name": kind, "template": template, "discrete": {"Ts": 1.0}},
        "experiments": [{"name": "e", "time": t.tolist(), "inputs": {"u": u.tolist()}, "outputs": {"y": y.tolist()}}],
        "method": method, "options": options})


def test_expanded_template_is_the_one_step_predictor():
    """x[k+1] = f(x[k], u[k], y[k]) from x = 0 gives ŷ = (1 − A/C) y + (B/C) u (scipy, zero start)."""
    model = Model.model_validate({"template": {"kind": "armax", "na": 2, "nb": 3, "nc": 1, "nk": 2},
                                  "discrete": {"Ts": 1.0},
                                  "parameters": [{"name": "a1", "value": 0}]})
    assert model.states == ["y_x1", "y_x2", "y_x3", "y_x4"] and model.inputs == ["u", "y_measured"]
    cm = compile_model(model)
    a, b, c = [1.0, -1.2, 0.5], [0.0, 0.0, 0.8, -0.3, 0.1], [1.0, 0.6]     # nk = 2: b1 multiplies q⁻²
    p = {"a1": a[1], "a2": a[2], "b1": b[2], "b2": b[3], "b3": b[4], "c1": c[1]}
    rng = np.random.default_rng(0)
    u, y = rng.standard_normal(50), rng.standard_normal(50)
    x = np.zeros(cm.nx)
    pred = []
    for k in range(50):
        pred.append(x[0])
        x = np.array(cm.rhs(x, [u[k], y[k]], [p[n] for n in cm.parameters], 0.0)).ravel()
    c_minus_a = np.polysub(c + [0.0], a)      # same length, descending powers of q⁻¹
    expected = signal.lfilter(c_minus_a, c, y) + signal.lfilter(b, c, u)
    assert np.allclose(pred, expected, atol=1e-12)


def test_armax_by_prediction_error_is_unbiased_where_arx_is_not():
    """Over 4 noise seeds: every ARMAX coefficient within 4 standard errors of the truth and the
    pooled z-scores of unit size; ARX (equation error) on the same data misses a1 by > 5 of its own
    standard errors every time, because the coloured noise C e correlates with its regressor."""
    z_armax, arx_bias, armax_bias = [], [], []
    for seed in range(4):
        t, u, y = armax_data(seed)
        armax = fit_model(request(t, u, y, "armax", "single_shooting", robust_covariance="never"))
        assert armax.success and armax.quality == "good", armax.message
        for name, truth in TRUTH.items():
            est = armax.parameters[name]
            z = (est.value - truth) / est.stderr
            assert abs(z) < 4, (seed, name, z)
            z_armax.append(z)
        # the predictor started from the ARX least-squares estimate (c = 0)
        assert armax.parameters["c1"].initial == 0.0 and armax.parameters["a1"].initial != 0.0
        arx = fit_model(request(t, u, y, "arx", "equation_error"))
        # converged, but biased, and the instrumental-variable check says so (it was `good` before)
        assert arx.solver.return_status in ("Linear_Least_Squares", "Solve_Succeeded") and not arx.success
        assert "a1" in [w for w in arx.warnings if w.code == "errors_in_variables_bias"][0].detail["parameters"]
        z_arx = (arx.parameters["a1"].value - TRUTH["a1"]) / arx.parameters["a1"].stderr
        assert abs(z_arx) > 5, (seed, z_arx)
        arx_bias.append(arx.parameters["a1"].value - TRUTH["a1"])
        armax_bias.append(armax.parameters["a1"].value - TRUTH["a1"])
    assert 0.5 < np.sqrt(np.mean(np.square(z_armax))) < 1.6
    assert abs(np.mean(armax_bias)) < 0.2 * abs(np.mean(arx_bias))


def test_armax_needs_output_error_and_the_measured_output():
    t, u, y = armax_data(0, n=200)
    with pytest.raises(DataError, match="single_shooting"):
        fit_model(request(t, u, y, "armax", "equation_error"))
    req = request(t, u, y, "armax", "single_shooting")
    req.experiments[0].outputs = {}
    with pytest.raises(DataError) as info:
        fit_model(req)
    assert info.value.field == "experiments[0].inputs.y_measured"


def test_armax_parameters_must_belong_to_the_template():
    with pytest.raises(ValueError, match="not part of the ARMAX template"):
        Model.model_validate({"template": {"kind": "armax", "na": 1, "nb": 1, "nc": 1}, "discrete": {"Ts": 1.0},
                              "parameters": [{"name": "d1", "value": 0}]})
