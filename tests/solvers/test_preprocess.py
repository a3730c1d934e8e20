"""Window, detrend and decimation with anti-aliasing; the piecewise-constant input hint."""
import numpy as np
import scipy.signal as ss

from greyfit.schemas import Experiment, FitRequest
from greyfit.solvers.fit import fit_model
from greyfit.solvers.data.preprocess import anti_alias_taps, preprocess_experiment, zero_phase_filter
from tests.systems import msd_input, msd_model, simulate_msd


def test_anti_alias_filter_is_scipys_fir_decimation():
    x = np.random.default_rng(0).standard_normal(3000)
    for q in (2, 5, 10):
        assert np.max(np.abs(anti_alias_taps(q) - ss.firwin(20 * q + 1, 1 / q, window="hamming"))) < 1e-14
        ours = zero_phase_filter(x, anti_alias_taps(q))[::q]
        ref = ss.decimate(x, q, ftype="fir")
        edge = 20 // 2 + 1     # the two differ only in how the ends are extended
        assert ours.size == ref.size and np.max(np.abs(ours[edge:-edge] - ref[edge:-edge])) < 1e-12


def _msd_record(t, noise, seed, hum=0.0):
    rng = np.random.default_rng(seed)
    x = simulate_msd(t)
    out = {n: x[i] + noise * rng.standard_normal(t.size) + hum * np.sin(2 * np.pi * 90 * t)
           for i, n in enumerate(("x", "v"))}
    return {"name": "e", "time": t.tolist(), "inputs": {"u": msd_input(t).tolist()},
            "outputs": {k: v.tolist() for k, v in out.items()}}


def _fit(exp):
    return fit_model(FitRequest.model_validate({"model": msd_model(), "experiments": [exp],
                                                "options": {"substeps": 2}}))


def test_decimating_1khz_by_10_gives_the_estimates_of_the_100hz_record():
    """A 1 kHz record with white noise and a 90 Hz hum (which would alias to 10 Hz) decimated by 10,
    against a 100 Hz record of the same motion with the noise an anti-aliased acquisition leaves."""
    fast = np.linspace(0, 10, 10001)
    sigma = 0.02
    raw = _msd_record(fast, sigma, seed=1, hum=0.05)
    dec = _fit({**raw, "preprocess": {"decimate": 10}})
    assert dec.preprocessing.experiments[0].samples_out == 1001
    ref = _fit(_msd_record(fast[::10], sigma / np.sqrt(10), seed=2))
    for name in ("c", "k"):
        a, b = dec.parameters[name], ref.parameters[name]
        assert abs(a.value - b.value) < 3 * np.hypot(a.stderr, b.stderr), (name, a, b)
        assert abs(a.value - {"c": 0.8, "k": 5.0}[name]) < 4 * a.stderr
    # without the filter the hum aliases into the band: plain subsampling fits far worse
    plain = _fit({**raw, "preprocess": {"window": [0, 10]}, "time": fast[::10].tolist(),
                  "inputs": {"u": raw["inputs"]["u"][::10]},
                  "outputs": {k: v[::10] for k, v in raw["outputs"].items()}})
    assert plain.metrics.rmse["x"] > 3 * dec.metrics.rmse["x"]


def test_window_and_linear_detrend_are_applied_to_every_series_and_reported():
    t = np.linspace(0, 4, 401)
    exp = Experiment.model_validate({
        "name": "e", "time": t.tolist(), "inputs": {"u": (np.sin(3 * t) + 2.0 + 0.5 * t).tolist()},
        "outputs": {"x": (np.cos(2 * t) - 1.0 + 0.25 * t).tolist()},
        "preprocess": {"window": [1.0, 3.0], "detrend": "linear"}})
    new, report = preprocess_experiment(exp, "experiments[0]")
    keep = (t >= 1.0) & (t <= 3.0)
    tt = t[keep]
    assert new.time == tt.tolist() and report.samples_out == keep.sum() and new.preprocess is None
    for group, name, series in (("inputs", "u", np.sin(3 * tt) + 2.0 + 0.5 * tt),
                                ("outputs", "x", np.cos(2 * tt) - 1.0 + 0.25 * tt)):
        slope, intercept = np.polyfit(tt - tt[0], series, 1)
        assert np.allclose(report.removed_trend[f"{group}.{name}"], [intercept, slope], rtol=1e-10)
        got = np.array(getattr(new, group)[name])
        assert np.allclose(got, series - intercept - slope * (tt - tt[0]), atol=1e-12)
        assert abs(got.mean()) < 1e-12


def test_a_held_input_with_foh_interpolation_gets_a_hint():
    t = np.linspace(0, 10, 201)
    prbs = np.repeat(np.random.default_rng(0).choice([-1.0, 1.0], 21), 10)[:201]
    x = np.vstack([np.zeros(201), np.zeros(201)])
    exp = {"name": "e", "time": t.tolist(), "inputs": {"u": prbs.tolist()},
           "outputs": {"x": (x[0] + 0.01 * np.random.default_rng(1).standard_normal(201)).tolist()}}
    body = {"model": msd_model(), "experiments": [exp], "method": "equation_error"}
    body["model"]["outputs"] = {"x": "x"}
    body["model"]["parameters"] = [{"name": n, "value": v, "fixed": True} for n, v in
                                   (("m", 2.0), ("c", 0.8), ("k", 5.0))]
    # the default (auto) holds it; forcing foh gets the hint, and a warning that counts (issue 22)
    res = fit_model(FitRequest.model_validate(body))
    assert res.preprocessing.hints == [] and res.preprocessing.input_interpolation == {"u": "zoh"}
    body["options"] = {"input_interpolation": "foh"}
    res = fit_model(FitRequest.model_validate(body))
    assert [h.code for h in res.preprocessing.hints] == ["input_looks_held"]
    assert "input_held_fitted_linear" in {w.code for w in res.warnings} and res.quality == "suspect"
    body["options"] = {"input_interpolation": "zoh"}
    assert fit_model(FitRequest.model_validate(body)).preprocessing.hints == []
    body["experiments"][0]["inputs"]["u"] = np.sin(t).tolist()
    body["options"] = {}
    res = fit_model(FitRequest.model_validate(body))
    assert res.preprocessing.hints == [] and res.preprocessing.input_interpolation == {"u": "foh"}
