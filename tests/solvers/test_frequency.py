"""Frequency-response fitting against seed 001's closed loop, truth simulated with scipy."""
import numpy as np
import pytest

from greyfit.schemas.frequency import FrequencyData, FrequencyFitRequest, SineTest
from greyfit.solvers.errors import DataError, ModelDefinitionError
from greyfit.solvers.frequency import fit_frequency_response
from greyfit.solvers.frequency.data import prepare_frequency_data
from greyfit.solvers.frequency.levy import levy_fit
from greyfit.solvers.frequency.polynomials import compile_transfer_function
from greyfit.solvers.frequency.sine_tests import response_from_sine_tests
from greyfit.solvers.frequency.stability import routh_first_column
from greyfit.solvers.model.parameters import build_layout
from tests.frequency_systems import (
    NAMES,
    OMEGA,
    TRUTH,
    closed_loop,
    frequency_data,
    response,
    seed001_model,
    sine_records,
)

GUESS = {n: 1.5 * v for n, v in TRUTH.items()}


def _fit(model: dict, data: list[dict], **options):
    return fit_frequency_response(FrequencyFitRequest.model_validate(
        {"model": model, "data": data, "options": options}))


def _relative_errors(result, truth: dict) -> np.ndarray:
    return np.array([result.parameters[n].value / truth[n] - 1 for n in truth])


def _max_real_pole(p: dict, kp: float, ki: float) -> float:
    return float(np.max(np.roots(np.trim_zeros(closed_loop(p, kp, ki)[1], "b")).real))


def test_truth_is_stable_in_both_loops_and_routh_satisfying():
    assert TRUTH["a1"] * TRUTH["a2"] > TRUTH["a3"] > 0
    assert _max_real_pole(TRUTH, 1, 1) < -0.2 and _max_real_pole(TRUTH, 1.65, 0) < -0.2


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_all_five_parameters_within_two_percent_and_loop_stable(seed):
    result = _fit(seed001_model(GUESS), [frequency_data(TRUTH, 1, 1, seed=seed, name="pi")])
    assert result.success, result.message
    assert np.max(np.abs(_relative_errors(result, TRUTH))) < 0.02
    fr = result.frequency_response
    assert fr.stable and fr.loops[0].max_real_part < 0
    assert all(v > 0 for v in fr.loops[0].routh_first_column)
    # covariance from the relative residual: the 2 % noise gives stderr of a few tenths of a percent
    assert result.covariance is not None
    for n in NAMES:
        assert 0 < result.parameters[n].stderr / TRUTH[n] < 0.02
    # reported response is the model's: compare with scipy at the fitted values
    fitted = {n: result.parameters[n].value for n in NAMES}
    g = response(fitted, 1, 1, OMEGA)
    d = fr.data[0]
    np.testing.assert_allclose(np.array(d.fitted_real) + 1j * np.array(d.fitted_imag), g, rtol=1e-9)
    assert d.zeros_imag and max(abs(z) for z in d.zeros_imag) == pytest.approx(np.sqrt(24 / 2), rel=0.02)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_joint_fit_with_a_second_controller(seed):
    data = [frequency_data(TRUTH, 1, 1, seed=seed, name="pi"),
            frequency_data(TRUTH, 1.65, 0, seed=100 + seed, name="p_only")]
    result = _fit(seed001_model(GUESS), data)
    assert result.success, result.message
    assert np.max(np.abs(_relative_errors(result, TRUTH))) < 0.02
    fr = result.frequency_response
    assert [lp.setting for lp in fr.loops] == ["pi", "p_only"] and fr.stable
    # Ki = 0: the integrator of C cancels the zero at s = 0 of the loop, leaving 4 poles
    assert len(fr.data[1].denominator) == 5 and len(fr.data[0].denominator) == 6


@pytest.mark.parametrize("stability", ["routh", "penalty"])
def test_start_violating_routh_ends_satisfying_it(stability):
    bad = {"a1": 1.0, "a2": 5.0, "a3": 40.0, "b1": 1.0, "b2": 10.0}
    assert bad["a1"] * bad["a2"] < bad["a3"] and _max_real_pole(bad, 1, 1) > 0   # really a bad start
    result = _fit(seed001_model(bad), [frequency_data(TRUTH, 1, 1, seed=3, name="pi")],
                  levy_start=False, stability=stability)
    p = {n: result.parameters[n].value for n in NAMES}
    assert result.success, result.message
    assert p["a1"] * p["a2"] - p["a3"] >= 0.01 - 1e-6
    assert result.frequency_response.stable and _max_real_pole(p, 1, 1) < 0
    assert np.max(np.abs(_relative_errors(result, TRUTH))) < 0.02


def test_stability_of_extra_controller_settings_is_enforced():
    """Seed 001's second trick: another gain setting must also give a stable loop (no data needed).

    (Kp, Ki) = (10, 10) is unstable at the truth, so the constraint must pull the estimate away
    from it and say so; (3, 0) is stable at the truth and leaves the estimate alone.
    """
    data = [frequency_data(TRUTH, 1, 1, seed=4, name="pi")]
    assert _max_real_pole(TRUTH, 10, 10) > 0 and _max_real_pole(TRUTH, 3, 0) < 0
    forced = _fit(seed001_model(GUESS), data, also_stable_with=[{"Kp": 10, "Ki": 10}])
    fitted = {n: forced.parameters[n].value for n in NAMES}
    assert _max_real_pole(fitted, 10, 10) < 0 and forced.frequency_response.loops[1].stable
    assert "stability constraint active" in forced.covariance_note
    free = _fit(seed001_model(GUESS), data, also_stable_with=[{"Kp": 3, "Ki": 0}])
    assert np.max(np.abs(_relative_errors(free, TRUTH))) < 0.02


@pytest.mark.parametrize("cost,tol", [("log", 0.02), ("log1p_abs_error", 0.05), ("complex", 0.05)])
def test_other_costs(cost, tol):
    """log|Ĝ/G| + phase matches the relative noise; the seed's log(|Ĝ-G|+1) and plain complex
    least squares weight the large-|G| frequencies, so they are less precise (measured: up to 2.7 %)."""
    result = _fit(seed001_model(GUESS), [frequency_data(TRUTH, 1, 1, seed=0, name="pi")], cost=cost)
    assert result.success and result.frequency_response.stable
    assert np.max(np.abs(_relative_errors(result, TRUTH))) < tol


def test_seed_001_numbers_levy_biased_then_nonlinear_fit_recovers():
    """Seed 001 as the document gives it.

    How we read its numbers: the slides write P = (b1 s² + b2)/(...), with the high-frequency
    asymptote |G| ≈ b1/ω² and the zero at ω0 = sqrt(b2/b1); its data section and MATLAB code swap
    the names (their "b2" = 33.2224 is the high-frequency coefficient, "b1" = ω0² b2). We keep the
    slides' names: b1 = 33.2224 (s² coefficient), ω0 = 21.135 rad/s, hence b2 = ω0² b1 = 14 840.
    The document prints 16 627 for that product, which is not 21.135² × 33.2224 (it would need
    ω0 = 22.37); we trust the two measured quantities and derive the product. As in the document,
    b1 and b2 are fixed from that pre-processing and a1, a2, a3 are estimated; their values are not
    printed, so we choose a = (20, 500, 2000) (a1 a2 > a3; both loops stable). The document picks its
    41 frequencies at random in [10^-1, 10^3]; we use 41 log-spaced ones in the same range.
    """
    truth = {"a1": 20.0, "a2": 500.0, "a3": 2000.0, "b1": 33.2224, "b2": 21.135 ** 2 * 33.2224}
    assert truth["b2"] == pytest.approx(14840, rel=1e-3)
    guess = dict(truth, a1=30.0, a2=750.0, a3=3000.0)
    model = seed001_model(guess, fixed=("b1", "b2"))
    levy_a3, fits = [], []
    for seed in range(4):
        data = [frequency_data(truth, 1, 1, seed=seed, name="pi")]
        request = FrequencyFitRequest.model_validate({"model": model, "data": data})
        tf = compile_transfer_function(request.model)
        sets = prepare_frequency_data(request.data, request.model)
        layout = build_layout(request.model, [s.name for s in sets])
        levy = levy_fit([tf.loop("pi", sets[0].constants)], sets, layout, iterations=0, constrained=False)
        levy_a3.append(dict(zip(layout.labels, levy.theta))["a3"])
        result = fit_frequency_response(request)
        fits.append(result)
    levy_a3 = np.array(levy_a3)
    # plain Levy (the document's convex problem without its constraints): a3 even negative
    assert np.any(levy_a3 < 0), levy_a3
    assert np.all(np.abs(levy_a3 / truth["a3"] - 1) > 0.5), levy_a3
    for result in fits:
        assert result.success and result.frequency_response.stable
        errors = [result.parameters[n].value / truth[n] - 1 for n in ("a1", "a2", "a3")]
        assert np.max(np.abs(errors)) < 0.02, errors
        assert result.frequency_response.levy_start is not None


def test_sine_tests_give_the_frequency_response():
    omegas = [0.3, 3.0, 30.0, 300.0]
    records = sine_records(TRUTH, 1, 1, omegas, noise=0.0, seed=0)
    omega, g = response_from_sine_tests([SineTest.model_validate(r) for r in records], "data[0].sine_tests")
    np.testing.assert_allclose(omega, omegas)
    np.testing.assert_allclose(g, response(TRUTH, 1, 1, np.array(omegas)), rtol=1e-3)


def test_routh_column_agrees_with_the_poles():
    rng = np.random.default_rng(0)
    for _ in range(200):
        den = np.concatenate([[1.0], rng.uniform(0.05, 3.0, 5)])
        stable = np.max(np.roots(den).real) < 0
        assert (min(routh_first_column(den)) > 0) == stable


def _data(**changes) -> dict:
    d = frequency_data(TRUTH, 1, 1, omega=np.array([1.0, 2.0, 3.0, 4.0]), level=0.0)
    d.update(changes)
    return d


@pytest.mark.parametrize("data,field,fragment", [
    (_data(omega=[0.0, 2.0, 3.0, 4.0]), "data[0].omega", "positive"),
    (_data(omega=[1.0, 3.0, 2.0, 4.0]), "data[0].omega", "strictly increasing"),
    (_data(real=[1.0, 2.0]), "data[0].real", "2 values, omega has 4"),
    (_data(gain=[1.0] * 4), "data[0]", "exactly one of"),
    (_data(constants={"Kd": 1.0}), "data[0].constants.Kd", "not a model constant"),
])
def test_bad_data_names_the_field(data, field, fragment):
    with pytest.raises(DataError) as err:
        prepare_frequency_data([FrequencyData.model_validate(data)], FrequencyFitRequest.model_validate(
            {"model": seed001_model(GUESS), "data": [data]}).model)
    assert err.value.field == field and fragment in err.value.message


def test_improper_transfer_function_is_refused():
    model = seed001_model(GUESS)
    model["numerator"] = ["b1", "b2", "0", "0", "0", "0"]
    with pytest.raises(ModelDefinitionError) as err:
        compile_transfer_function(FrequencyFitRequest.model_validate({"model": model, "data": [_data()]}).model)
    assert err.value.field == "model.numerator" and "improper" in err.value.message


def test_loop_with_overflowing_coefficients_is_reported_unknown_not_stable():
    """Ki = 1e308 makes the closed loop's coefficients overflow: no poles, no Routh column, stable
    false (np.roots raised on them, a 500 through the service)."""
    from greyfit.solvers.frequency.fit import _loop_report
    from greyfit.solvers.frequency.stability import is_stable, poles

    request = FrequencyFitRequest.model_validate({"model": seed001_model(TRUTH), "data": [_data()]})
    tf = compile_transfer_function(request.model)
    p = np.array([TRUTH[n] for n in NAMES])
    report = _loop_report(tf.loop("huge", {"Kp": 1.0, "Ki": 1e308}), p)
    assert report.max_real_part is None and report.stable is False
    assert report.poles_real == [] and report.routh_first_column == []
    assert _loop_report(tf.loop("pi", {"Kp": 1.0, "Ki": 1.0}), p).stable is True   # the truth's loop
    assert not is_stable(np.array([1.0, np.inf, 2.0])) and np.isnan(poles(np.array([1.0, np.nan])).real).all()
