"""Check experiments against a compiled model and turn them into numpy arrays."""
from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator
from contextvars import ContextVar
from dataclasses import dataclass

import numpy as np

from greyfit.schemas.experiment import Experiment
from greyfit.schemas.online import measured_output_inputs
from greyfit.solvers.errors import DataError
from greyfit.solvers.model.compiler import CompiledModel

# Beyond this, squares and sums of squares overflow double precision.
MAX_ABS_VALUE = 1e100


@dataclass
class ExperimentData:
    """Arrays of one experiment; missing output samples are NaN and masked out."""

    name: str
    t: np.ndarray            # (N,)
    u: np.ndarray            # (nu, N)
    y: np.ndarray            # (ny, N), NaN where missing
    x0_known: dict[int, float]
    derivatives: dict[int, np.ndarray]  # state index -> (N,), NaN where missing

    @property
    def n(self) -> int:
        """Number of samples.

        Returns
        -------
        int
            Length of the time grid `t`.
        """
        return self.t.size

    @property
    def mask(self) -> np.ndarray:
        """Where outputs were measured.

        Returns
        -------
        numpy.ndarray
            Boolean array, shape (ny, N): True where `y` is finite.
        """
        return np.isfinite(self.y)


def series_array(values) -> np.ndarray:
    """A request's series (a list; None for a missing sample) as a float array, NaN where missing.

    Within `prepared_once` each list is converted once and the array shared, read-only: a fit reads
    a record's series for the input check, the arrays of its solve and the noise-level check, and
    converting a 200 000-sample list costs ~5 ms each time.

    Parameters
    ----------
    values : sequence of float or None
        The series as received.

    Returns
    -------
    numpy.ndarray
        Shape (len(values),); read-only within `prepared_once`.
    """
    shared = _PREPARED.get()
    if shared is None:
        return np.array(values, dtype=float)
    key = ("series", id(values))
    hit = shared.get(key)
    if hit is not None and hit[0] is values:   # the entry holds the list: its id is not reused meanwhile
        return hit[1]
    arr = np.array(values, dtype=float)
    arr.flags.writeable = False
    shared[key] = (values, arr)
    return arr


def _series(values, where: str, n: int, allow_missing: bool) -> np.ndarray:
    if len(values) != n:
        raise DataError(f"{len(values)} values, time has {n}; give one value per time sample", where)
    arr = series_array(values)   # None becomes NaN
    if arr.size and np.max(np.abs(arr)) <= MAX_ABS_VALUE:   # complete and in range: nothing to report
        return arr
    finite = np.isfinite(arr)
    bad = [] if finite.all() else [int(i) for i in np.flatnonzero(~finite) if values[i] is not None]
    if bad:
        raise DataError(f"value at index {bad[0]} is {values[bad[0]]}; only finite numbers "
                        "(or null for a missing sample) are allowed", where)
    huge = np.flatnonzero(np.abs(arr) > MAX_ABS_VALUE)   # NaN compares False
    if huge.size:
        raise DataError(f"value at index {int(huge[0])} is {values[int(huge[0])]:g}; magnitudes above "
                        f"{MAX_ABS_VALUE:g} overflow when squared: change the units", where)
    if not allow_missing and not finite.all():
        i = int(np.flatnonzero(np.isnan(arr))[0])
        raise DataError(f"missing value (null) at index {i}; inputs must be complete: "
                        "interpolate or trim the experiment", where)
    return arr


def prepare_experiment(exp: Experiment, cm: CompiledModel, index: int) -> ExperimentData:
    """Validate one experiment; every error names `experiments[i].<field>`.

    Parameters
    ----------
    exp : Experiment
        The experiment as received.
    cm : CompiledModel
        The compiled model the experiment must fit (inputs, outputs, states).
    index : int
        Position of the experiment in the request, for the field paths.

    Returns
    -------
    ExperimentData
        Time grid, inputs (nu, N), outputs (ny, N) with NaN for missing samples, known initial states
        by state index, and measured derivatives by state index. An ARMAX input fed by a measured
        output is filled from that output.

    Raises
    ------
    DataError
        On a time grid that is not finite, too large or not strictly increasing; an unknown or
        missing input; an unknown output or one with every sample null; a series of the wrong length,
        with a non-finite value, a magnitude above `MAX_ABS_VALUE` or (inputs) a missing sample; an
        unknown or non-finite initial state; a derivative of an unknown state.
    """
    base = f"experiments[{index}]"
    t = series_array(exp.time)
    if not np.all(np.isfinite(t)):
        i = int(np.flatnonzero(~np.isfinite(t))[0])
        raise DataError(f"time[{i}] is not a finite number", f"{base}.time")
    if np.any(np.abs(t) > MAX_ABS_VALUE):
        i = int(np.flatnonzero(np.abs(t) > MAX_ABS_VALUE)[0])
        raise DataError(f"time[{i}] = {t[i]:g} is too large; change the time unit or origin", f"{base}.time")
    steps = np.diff(t)
    if np.any(steps <= 0):
        i = int(np.flatnonzero(steps <= 0)[0])
        raise DataError(f"time must increase strictly; time[{i + 1}] = {t[i + 1]} follows "
                        f"time[{i}] = {t[i]}", f"{base}.time")
    n = t.size

    unknown = sorted(set(exp.inputs) - set(cm.inputs))
    if unknown:
        raise DataError(f"'{unknown[0]}' is not an input of the model (inputs: {cm.inputs})",
                        f"{base}.inputs.{unknown[0]}")
    u = np.zeros((cm.nu, n))
    fed = measured_output_inputs(cm.model.template)   # ARMAX: the predictor reads the measured output
    for i, name in enumerate(cm.inputs):
        if name not in exp.inputs and fed.get(name) in exp.outputs:
            u[i] = _series(exp.outputs[fed[name]], f"{base}.outputs.{fed[name]}", n, allow_missing=False)
            continue
        if name not in exp.inputs:
            raise DataError(f"no data for model input '{name}'; every input needs a series",
                            f"{base}.inputs.{name}")
        u[i] = _series(exp.inputs[name], f"{base}.inputs.{name}", n, allow_missing=False)

    unknown = sorted(set(exp.outputs) - set(cm.outputs))
    if unknown:
        raise DataError(f"'{unknown[0]}' is not an output of the model (outputs: {cm.outputs}); "
                        "declare it in model.outputs", f"{base}.outputs.{unknown[0]}")
    y = np.full((cm.ny, n), np.nan)
    for i, name in enumerate(cm.outputs):
        if name in exp.outputs:
            y[i] = _series(exp.outputs[name], f"{base}.outputs.{name}", n, allow_missing=True)
            if np.isnan(y[i]).all():
                raise DataError("every sample is null; give data or leave the output out",
                                f"{base}.outputs.{name}")

    x0 = {}
    for name, value in exp.initial_state.items():
        if name not in cm.states:
            raise DataError(f"'{name}' is not a state (states: {cm.states})",
                            f"{base}.initial_state.{name}")
        if not math.isfinite(value) or abs(value) > MAX_ABS_VALUE:
            raise DataError(f"must be a finite number of magnitude at most {MAX_ABS_VALUE:g}",
                            f"{base}.initial_state.{name}")
        x0[cm.states.index(name)] = float(value)

    derivatives = {}
    for name, values in exp.derivatives.items():
        if name not in cm.states:
            raise DataError(f"'{name}' is not a state (states: {cm.states})",
                            f"{base}.derivatives.{name}")
        derivatives[cm.states.index(name)] = _series(
            values, f"{base}.derivatives.{name}", n, allow_missing=True)

    for arr in (t, u, y, *derivatives.values()):   # shared by the fit's steps (`prepared_once`): never changed
        arr.flags.writeable = False
    return ExperimentData(exp.name, t, u, y, x0, derivatives)


# (experiments, compiled model, require_outputs) -> their prepared arrays, while a fit runs
_PREPARED: ContextVar[dict | None] = ContextVar("greyfit_prepared", default=None)


@contextlib.contextmanager
def prepared_once() -> Iterator[None]:
    """Within: `prepare_experiments` of the same experiments list for the same compiled model gives
    the same `ExperimentData` (read-only arrays). A fit prepares its records for the solve, the step
    choice, the input reading and the lack-of-fit screen: converting a 200 000-sample series from the
    request's list costs milliseconds each time, and the screen finds the solve's Jacobian at the
    optimum by the records' identity. Nested uses share the outer one; on leaving, nothing is kept.

    Yields
    ------
    None
        Within the block, prepared records are shared.
    """
    if _PREPARED.get() is not None:
        yield
        return
    token = _PREPARED.set({})
    try:
        yield
    finally:
        _PREPARED.reset(token)


def prepare_experiments(experiments: list[Experiment], cm: CompiledModel,
                        require_outputs: bool = True) -> list[ExperimentData]:
    """Checked arrays of every experiment; `require_outputs=False` when nothing is fitted (simulation).

    Parameters
    ----------
    experiments : list of Experiment
        The experiments as received.
    cm : CompiledModel
        The compiled model.
    require_outputs : bool, optional
        Require every model output to have data in at least one experiment.

    Returns
    -------
    list of ExperimentData
        One per experiment, in order (see `prepare_experiment`).

    Raises
    ------
    DataError
        On a duplicated experiment name (``experiments[i].name``), on an output without data in any
        experiment (``experiments[*].outputs.<name>``), or as `prepare_experiment`.
    """
    memo = _PREPARED.get()
    key = (id(experiments), id(cm), require_outputs)
    if memo is not None and key in memo and memo[key][0] is experiments and memo[key][1] is cm:
        return list(memo[key][2])
    names = [e.name for e in experiments]
    for i, name in enumerate(names):
        if names.index(name) != i:
            raise DataError(f"name '{name}' is used twice; experiment names must be unique",
                            f"experiments[{i}].name")
    data = [prepare_experiment(e, cm, i) for i, e in enumerate(experiments)]
    for j, out in enumerate(cm.outputs if require_outputs else []):
        if not any(np.isfinite(d.y[j]).any() for d in data):
            raise DataError(f"output '{out}' has no data in any experiment; give its samples "
                            "or remove it from model.outputs", f"experiments[*].outputs.{out}")
    if memo is not None:   # the entry holds both objects: their ids stay theirs while it lives
        memo[key] = (experiments, cm, data)
    return list(data)


def fill_missing(series: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Linear interpolation over NaN gaps (used only to initialise, never to fit).

    Parameters
    ----------
    series : numpy.ndarray
        Series with NaN at missing samples (at least one finite), shape (N,).
    t : numpy.ndarray
        Sample times, shape (N,).

    Returns
    -------
    numpy.ndarray
        A copy with the gaps filled linearly (held constant beyond the first and last finite sample).
    """
    ok = np.isfinite(series)
    if ok.all():
        return series.copy()
    return np.interp(t, t[ok], series[ok])
