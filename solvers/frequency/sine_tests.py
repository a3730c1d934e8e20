"""Frequency response from raw sine-test records: least squares on sin/cos components (the course notes
on parameter estimation from frequency data).

With ``u(t) = Σ Im(U_i e^{jω_i t})`` and ``y(t) = Σ Im(Y_i e^{jω_i t})`` in steady state,
``Y_i = G(jω_i) U_i``. Regressing u and y on ``[sin ω_i t, cos ω_i t, 1]`` gives
``Im(X e^{jωt}) = Re X sin ωt + Im X cos ωt``, so ``X = (sin coefficient) + j (cos coefficient)``;
the course notes' ``s_i = |G| cos∠G`` and ``c_i = |G| sin∠G`` are Re G and Im G for a unit input.
The constant column absorbs an offset (e.g. the shifted rest position of a marginally stable plant).
"""
from __future__ import annotations

import numpy as np

from greyfit.schemas.frequency import SineTest
from greyfit.solvers.errors import DataError


def _as_array(values, where: str) -> np.ndarray:
    arr = np.asarray(values, dtype=float)
    if not np.all(np.isfinite(arr)):
        raise DataError("contains a non-finite value; remove or repair the sample", where)
    return arr


def sine_test_response(test: SineTest, where: str) -> tuple[np.ndarray, np.ndarray]:
    """(omega, G(jω)) of one record; several frequencies in one record are estimated jointly.

    Parameters
    ----------
    test : SineTest
        One record: frequencies (rad/s), time (s), input and output samples, settle time (s).
    where : str
        The record's field path, for error messages (e.g. ``data[0].sine_tests[1]``).

    Returns
    -------
    tuple of numpy.ndarray
        (omega (K,), complex G(jω) (K,)) in the record's frequency order.

    Raises
    ------
    DataError
        On a non-finite sample, input or output length unlike time, time not increasing, a frequency
        not positive, a record after `settle_time` shorter than one period of the lowest frequency, or
        an input with no component at one of the frequencies; the field is named.
    """
    omega = np.atleast_1d(_as_array(test.omega, f"{where}.omega"))
    t = _as_array(test.time, f"{where}.time")
    u = _as_array(test.input, f"{where}.input")
    y = _as_array(test.output, f"{where}.output")
    for name, arr in (("input", u), ("output", y)):
        if arr.size != t.size:
            raise DataError(f"{arr.size} values, time has {t.size}; give one value per time sample",
                            f"{where}.{name}")
    if np.any(np.diff(t) <= 0):
        raise DataError("time must be strictly increasing", f"{where}.time")
    if np.any(omega <= 0):
        raise DataError("every frequency must be positive (rad/s)", f"{where}.omega")
    keep = t >= test.settle_time
    t, u, y = t[keep], u[keep], y[keep]
    span = t[-1] - t[0] if t.size > 1 else 0.0
    if t.size < 2 * omega.size + 2 or span * omega.min() < 2 * np.pi:
        raise DataError(f"after settle_time {test.settle_time} s the record must cover at least one period "
                        f"of the lowest frequency ({2 * np.pi / omega.min():.4g} s) with enough samples; "
                        "record longer or lower settle_time", f"{where}.time")
    cols = [np.sin(w * t) for w in omega] + [np.cos(w * t) for w in omega] + [np.ones_like(t)]
    basis = np.column_stack(cols)
    coef, *_ = np.linalg.lstsq(basis, np.column_stack([u, y]), rcond=None)
    k = omega.size
    u_amp = coef[:k, 0] + 1j * coef[k:2 * k, 0]
    y_amp = coef[:k, 1] + 1j * coef[k:2 * k, 1]
    weak = np.abs(u_amp) <= 1e-9 * max(1.0, float(np.max(np.abs(u))))
    if np.any(weak):
        raise DataError(f"the input has no component at ω = {omega[np.argmax(weak)]:g} rad/s", f"{where}.input")
    return omega, y_amp / u_amp


def response_from_sine_tests(tests: list[SineTest], where: str) -> tuple[np.ndarray, np.ndarray]:
    """All records' estimates, sorted by frequency; a frequency measured twice is an error.

    Parameters
    ----------
    tests : list of SineTest
        The records.
    where : str
        Their field path (e.g. ``data[0].sine_tests``).

    Returns
    -------
    tuple of numpy.ndarray
        (omega, complex G(jω)), sorted by increasing frequency.

    Raises
    ------
    DataError
        On any error of `sine_test_response`, or when two records share a frequency.
    """
    omegas, responses = [], []
    for i, test in enumerate(tests):
        w, g = sine_test_response(test, f"{where}[{i}]")
        omegas.append(w)
        responses.append(g)
    omega = np.concatenate(omegas)
    g = np.concatenate(responses)
    order = np.argsort(omega)
    omega, g = omega[order], g[order]
    if np.any(np.diff(omega) <= 0):
        raise DataError("two records share a frequency; give each frequency once", where)
    return omega, g
