"""Check frequency data and turn every form (real/imag, gain/phase, sine tests) into G(jω)."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from greyfit.schemas.frequency import FrequencyData, LinearisedOdeModel, TransferFunctionModel
from greyfit.solvers.errors import DataError
from greyfit.solvers.frequency.sine_tests import response_from_sine_tests


@dataclass
class FrequencySet:
    name: str
    omega: np.ndarray
    response: np.ndarray           # complex G(jω)
    constants: dict[str, float] = field(default_factory=dict)


def _series(values, n: int, where: str) -> np.ndarray:
    arr = np.asarray(values, dtype=float)
    if arr.size != n:
        raise DataError(f"{arr.size} values, omega has {n}; give one value per frequency", where)
    if not np.all(np.isfinite(arr)):
        raise DataError("contains a non-finite value", where)
    return arr


def _check_omega(omega: np.ndarray, where: str) -> None:
    if omega.size == 0:
        raise DataError("no frequency given", where)
    if not np.all(np.isfinite(omega)):
        raise DataError("contains a non-finite value", where)
    bad = np.flatnonzero(omega <= 0)
    if bad.size:
        raise DataError(f"omega[{bad[0]}] = {omega[bad[0]]:g}: frequencies must be positive (rad/s); drop "
                        "the static point or give it as a small positive frequency", where)
    step = np.flatnonzero(np.diff(omega) <= 0)
    if step.size:
        i = step[0] + 1
        raise DataError(f"omega[{i}] = {omega[i]:g} is not above omega[{i - 1}] = {omega[i - 1]:g}; "
                        "frequencies must be strictly increasing: sort them and merge repeats", where)


def _measured(d: FrequencyData, where: str) -> tuple[np.ndarray, np.ndarray]:
    forms = [name for name, given in (("real/imag", d.real is not None or d.imag is not None),
                                      ("gain/phase_deg", d.gain is not None or d.phase_deg is not None),
                                      ("sine_tests", d.sine_tests is not None)) if given]
    if len(forms) != 1:
        raise DataError(f"give exactly one of real/imag, gain/phase_deg or sine_tests (got {forms or 'none'})",
                        where)
    if d.sine_tests is not None:   # the one form given
        if d.omega is not None:
            raise DataError("omega comes from the sine tests themselves; leave it out", f"{where}.omega")
        return response_from_sine_tests(d.sine_tests, f"{where}.sine_tests")
    if d.omega is None:
        raise DataError("omega is required with real/imag or gain/phase_deg", f"{where}.omega")
    omega = np.asarray(d.omega, dtype=float)
    _check_omega(omega, f"{where}.omega")
    n = omega.size
    if forms[0] == "real/imag":
        for name in ("real", "imag"):
            if getattr(d, name) is None:
                raise DataError("real and imag come together", f"{where}.{name}")
        g = _series(d.real, n, f"{where}.real") + 1j * _series(d.imag, n, f"{where}.imag")
    else:
        for name in ("gain", "phase_deg"):
            if getattr(d, name) is None:
                raise DataError("gain and phase_deg come together", f"{where}.{name}")
        gain = _series(d.gain, n, f"{where}.gain")
        if d.gain_unit == "dB":
            gain = 10.0 ** (gain / 20.0)
        elif np.any(gain < 0):
            raise DataError("an absolute gain is never negative; set gain_unit to 'dB' for decibels",
                            f"{where}.gain")
        g = gain * np.exp(1j * np.deg2rad(_series(d.phase_deg, n, f"{where}.phase_deg")))
    return omega, g


def prepare_frequency_data(data: list[FrequencyData],
                           model: TransferFunctionModel | LinearisedOdeModel) -> list[FrequencySet]:
    """Validated frequency sets; errors name the field (`data[0].omega`) and the fix.

    Parameters
    ----------
    data : list of FrequencyData
        The request's data sets, each in one form: real/imag, gain/phase_deg or sine tests.
    model : TransferFunctionModel or LinearisedOdeModel
        The model; the sets' `constants` must be among its constants.

    Returns
    -------
    list of FrequencySet
        One per data set: its name, ω (rad/s, strictly increasing), the complex response and its constants.

    Raises
    ------
    DataError
        On a repeated name, an unknown constant, none or several forms given, omega missing, not
        positive, not increasing or not finite, series lengths unlike omega, a negative absolute gain,
        or bad sine-test records.
    """
    sets, names = [], set()
    for i, d in enumerate(data):
        where = f"data[{i}]"
        if d.name in names:
            raise DataError(f"name '{d.name}' is used twice; give each data set its own name", f"{where}.name")
        names.add(d.name)
        unknown = sorted(set(d.constants) - set(model.constants))
        if unknown:
            raise DataError(f"'{unknown[0]}' is not a model constant (constants: {sorted(model.constants)}); "
                            "declare it in model.constants", f"{where}.constants.{unknown[0]}")
        omega, g = _measured(d, where)
        sets.append(FrequencySet(d.name, omega, g, dict(d.constants)))
    return sets
