"""Simulate a model with given parameters on experiments, and validation metrics against records.

The integrator and input interpolation are the fits' own (`OutputErrorModel`, `make_step`), so a
simulation of a fitted model reproduces the fit's simulated outputs to rounding.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from greyfit.schemas.experiment import Experiment
from greyfit.schemas.fit import FitOptions
from greyfit.schemas.model import Model
from greyfit.schemas.simulate import SimulatedExperiment, SimulateRequest, SimulateResult
from greyfit.schemas.validation import ExperimentValidation, InitialStateSource, OutputMetrics, ValidationResult
from greyfit.solvers.data.experiments import ExperimentData, prepare_experiments
from greyfit.solvers.data.refine import DEFAULT_FACTOR, refine_experiment, refine_options, refine_request
from greyfit.solvers.errors import DataError
from greyfit.solvers.methods.shooting import OutputErrorModel, sensitivity_jacobian
from greyfit.solvers.model.compiler import CompiledModel, compile_model
from greyfit.solvers.model.parameters import ParameterLayout

MAX_LM_ITERATIONS = 50


@dataclass
class Simulation:
    """Numeric simulation of one experiment (arrays; `to_public` makes the schema object)."""

    data: ExperimentData
    p: np.ndarray
    x0: np.ndarray
    states: np.ndarray          # (nx, N)
    outputs: np.ndarray         # (ny, N)
    source: InitialStateSource
    estimated: list[str] = field(default_factory=list)
    window: int | None = None
    predicted: np.ndarray | None = None
    horizon: int | None = None
    note: str | None = None


def default_estimate_window(n: int, nx: int) -> int:
    """A short leading window: 10 samples per state, at least 50, never more than the record.

    Parameters
    ----------
    n : int
        Number of samples in the record.
    nx : int
        Number of states.

    Returns
    -------
    int
        min(n, max(50, 10 nx)) samples.
    """
    return int(min(n, max(50, 10 * nx)))


def fixed_layout(p: np.ndarray, n_experiments: int) -> ParameterLayout:
    """A layout with nothing free: every experiment's parameter vector is `p`.

    Parameters
    ----------
    p : numpy.ndarray
        Physical parameter vector in declaration order, shape (np,).
    n_experiments : int
        Number of experiments sharing it.

    Returns
    -------
    ParameterLayout
        A layout with no free entry, `p` as its fixed base and an empty (np, 0) map per experiment.
    """
    empty = np.zeros(0)
    return ParameterLayout([], [], [], empty, empty, empty, empty, np.asarray(p, dtype=float),
                           [np.zeros((p.size, 0)) for _ in range(n_experiments)], {})


def parameter_vector(model: Model, parameters: dict[str, float], experiment: str) -> np.ndarray:
    """Physical parameter vector in declaration order for one experiment.

    `parameters` holds declared names (``k``) or per-experiment estimates (``k[exp1]``, which win
    for experiment ``exp1``); a parameter given neither way keeps the model's declared value.

    Parameters
    ----------
    model : Model
        The model whose declared parameters give the order and the default values.
    parameters : dict of str to float
        Values by declared name or by ``name[experiment]`` label.
    experiment : str
        Name of the experiment the vector is for.

    Returns
    -------
    numpy.ndarray
        One value per declared parameter, shape (np,).

    Raises
    ------
    DataError
        When a label is not a parameter of the model, when a parameter has per-experiment values but
        none for this experiment nor a shared one, or when a value is not finite; names
        ``parameters.<label>``.
    """
    declared = {p.name for p in model.parameters}
    for label in parameters:
        base = label.split("[", 1)[0]
        if base not in declared:
            raise DataError(f"'{label}' is not a parameter of the model (parameters: {sorted(declared)})",
                            f"parameters.{label}")
    values = []
    for p in model.parameters:
        copies = [k for k in parameters if k.startswith(f"{p.name}[")]
        if copies and f"{p.name}[{experiment}]" not in parameters and p.name not in parameters:
            raise DataError(f"'{p.name}' has per-experiment values {copies} but none for experiment "
                            f"'{experiment}'; give parameters['{p.name}'] (or '{p.name}[{experiment}]')",
                            f"parameters.{p.name}")
        v = parameters.get(f"{p.name}[{experiment}]", parameters.get(p.name, p.value))
        if not np.isfinite(v):
            raise DataError("must be a finite number", f"parameters.{p.name}")
        values.append(float(v))
    return np.array(values, dtype=float)


def estimate_initial_state(cm: CompiledModel, d: ExperimentData, p: np.ndarray, known: dict[int, float],
                           options: FitOptions, window: int, where: str) -> tuple[np.ndarray, str | None]:
    """Fit the initial states not in `known` to the first `window` samples, parameters fixed.

    Levenberg-Marquardt on the output-error residual with the fits' forward sensitivities
    (`sensitivity_jacobian`); starts from the first measured sample of directly measured states.

    Parameters
    ----------
    cm : CompiledModel
        The compiled model.
    d : ExperimentData
        The prepared experiment; only its first `window` samples are used.
    p : numpy.ndarray
        Physical parameter vector, shape (np,).
    known : dict of int to float
        Initial states already known, by state index; they stay fixed.
    options : FitOptions
        Integrator, substeps and input interpolation of the simulation.
    window : int
        Number of leading samples to fit on (capped at the record length).
    where : str
        Field path named in the errors (e.g. ``experiments[0].initial_state``).

    Returns
    -------
    x0 : ndarray
        The full initial state.
    note : str or None
        Set when the window leaves some initial state undetermined.

    Raises
    ------
    DataError
        When the window holds no measured output, or the model's outputs are not finite there with
        these parameters; names `where`.
    """
    w = int(min(window, d.n))
    wd = ExperimentData(d.name, d.t[:w], d.u[:, :w], d.y[:, :w], dict(known), {})
    if not np.isfinite(wd.y).any():
        free = [cm.states[i] for i in range(cm.nx) if i not in known]
        raise DataError(f"no measured output in the first {w} samples to estimate the initial state "
                        f"{free} from; give it in initial_state or lengthen estimate_window", where)
    oem = OutputErrorModel(cm, [wd], fixed_layout(p, 1), options)
    x0 = np.zeros(cm.nx)
    for out, state in cm.direct_outputs.items():   # first measured sample of a directly measured state
        row = wd.y[cm.outputs.index(out)]
        if np.isfinite(row).any():
            x0[cm.states.index(state)] = row[np.isfinite(row)][0]
    for i, v in known.items():
        x0[i] = v
    free_idx = oem.free_x0[0]
    if not free_idx:
        return x0, None

    def evaluate(x):
        jac, res, _ = sensitivity_jacobian(oem, np.zeros(0), [dict(zip(cm.states, x))])
        return jac, res, 0.5 * float(res @ res)

    jac, res, cost = evaluate(x0)
    if not (np.all(np.isfinite(jac)) and np.isfinite(cost)):
        # parameters near the float limits (1e308) overflow the simulation itself: nothing to fit
        raise DataError("the model's outputs are not finite over the first samples with these parameters, so "
                        "its initial state cannot be estimated; check the parameter values or give initial_state",
                        where)
    mu = 1e-3
    for _ in range(MAX_LM_ITERATIONS):
        jtj, jtr = jac.T @ jac, jac.T @ res
        damping = mu * np.maximum(np.diag(jtj), 1e-12 * max(1.0, float(np.trace(jtj))))
        step = -np.linalg.lstsq(jtj + np.diag(damping), jtr, rcond=None)[0]
        trial = x0.copy()
        trial[free_idx] += step * oem.xscale[free_idx]
        if not np.all(np.isfinite(trial)):
            mu *= 10
            continue
        jac_t, res_t, cost_t = evaluate(trial)
        if np.isfinite(cost_t) and cost_t <= cost:
            converged = cost - cost_t <= 1e-12 * max(cost, 1e-300) or np.linalg.norm(step) < 1e-10
            x0, jac, res, cost = trial, jac_t, res_t, cost_t
            mu = max(mu / 10, 1e-12)
            if converged:
                break
        else:
            mu *= 10
            if mu > 1e12:
                break
    sv = np.linalg.svd(jac, compute_uv=False) if jac.size and np.all(np.isfinite(jac)) else np.zeros(0)
    note = None
    if sv.size and sv[-1] <= 1e-8 * sv[0]:
        note = (f"the first {w} samples do not determine every initial state; lengthen "
                "estimate_window or give initial_state")
    return x0, note


def _resolve_initial_state(cm, d, p, provided, source_of_provided, options, window, where):
    """(x0, source, estimated state names, window or None, note)."""
    known = dict(d.x0_known)
    if len(known) == cm.nx:
        return np.array([known[i] for i in range(cm.nx)]), "experiment", [], None, None
    for name, value in (provided or {}).items():
        if name not in cm.states:
            raise DataError(f"'{name}' is not a state (states: {cm.states})", f"initial_states.{d.name}.{name}")
        if not np.isfinite(value):
            raise DataError("must be a finite number", f"initial_states.{d.name}.{name}")
        known.setdefault(cm.states.index(name), float(value))
    if len(known) == cm.nx:
        return np.array([known[i] for i in range(cm.nx)]), source_of_provided, [], None, None
    free = [cm.states[i] for i in range(cm.nx) if i not in known]
    x0, note = estimate_initial_state(cm, d, p, known, options, window, where)
    return x0, "estimated", free, int(min(window, d.n)), note


def k_step_ahead(oem: OutputErrorModel, e: int, p: np.ndarray, states: np.ndarray, k: int) -> np.ndarray:
    """ŷ(t | t-k) for every sample, as MATLAB's compare(.., k).

    The model restarts at every sample t-k from the measured states (directly measured states
    where the sample is present; the others, and gaps, from the free simulation) and runs k
    samples; the first k samples keep the free simulation.

    Parameters
    ----------
    oem : OutputErrorModel
        The output-error model over the experiments.
    e : int
        Index of the experiment.
    p : numpy.ndarray
        Physical parameter vector, shape (np,).
    states : numpy.ndarray
        Free-run simulated states of the experiment, shape (nx, N).
    k : int
        Prediction horizon in samples, ≥ 1.

    Returns
    -------
    numpy.ndarray
        Predicted outputs, shape (ny, N).
    """
    d, cm = oem.data[e], oem.cm
    pred_states = states.copy()
    m = d.n - k
    if m > 0:
        starts = states[:, :m].copy()
        for output, state in cm.direct_outputs.items():
            meas = d.y[cm.outputs.index(output), :m]
            i = cm.states.index(state)
            starts[i] = np.where(np.isfinite(meas), meas, starts[i])
        cols = (np.arange(m)[:, None] + np.arange(k)[None, :]).ravel()
        sim = oem.simulator(k).map(m)
        out = np.array(sim(starts, d.u[:, cols], d.u[:, cols + 1], np.repeat(p[:, None], cols.size, 1),
                           d.t[cols][None, :], (d.t[cols + 1] - d.t[cols])[None, :]))
        pred_states[:, k:] = out[:, k - 1::k]
    return oem.numeric_outputs(e, pred_states, p)


def simulate_arrays(model: Model, parameters: dict[str, float], experiments: list[Experiment],
                    options: FitOptions, initial_states: dict[str, dict[str, float]] | None = None,
                    estimate_window: int | None = None, horizon: int | None = None,
                    provided_source: dict[str, str] | None = None,
                    cm: CompiledModel | None = None) -> list[Simulation]:
    """The numeric core of `simulate_experiments` (see there); returns arrays per experiment.

    Parameters
    ----------
    model, parameters, experiments, options, initial_states, estimate_window, horizon
        As in `simulate_experiments`.
    provided_source : dict of str to str or None, optional
        Per experiment name, the `initial_state_source` reported for states given in
        `initial_states` (default ``"provided"``; validation uses ``"contiguous"``).
    cm : CompiledModel or None, optional
        The compiled `model`, when the caller has it already.

    Returns
    -------
    list of Simulation
        One per experiment: parameters, initial state and its source, states (nx, N), outputs (ny, N),
        the k-step predictions when `horizon` is set, and a note where the simulation diverged or the
        initial state is undetermined.

    Raises
    ------
    DataError
        When `initial_states` names an unknown experiment (``initial_states.<name>``), on a bad
        parameter (see `parameter_vector`), on a bad initial state, or when the experiments do not fit
        the model.
    """
    cm = cm or compile_model(model)
    data = prepare_experiments(experiments, cm, require_outputs=False)
    initial_states = initial_states or {}
    provided_source = provided_source or {}
    known_names = {e.name for e in experiments}
    for name in initial_states:
        if name not in known_names:
            raise DataError(f"no experiment is named '{name}' (experiments: {sorted(known_names)})",
                            f"initial_states.{name}")
    pvecs = [parameter_vector(model, parameters, d.name) for d in data]
    oem = OutputErrorModel(cm, data, fixed_layout(pvecs[0], len(data)), options)
    sims = []
    for e, d in enumerate(data):
        window = estimate_window or default_estimate_window(d.n, cm.nx)
        x0, source, estimated, used_window, note = _resolve_initial_state(
            cm, d, pvecs[e], initial_states.get(d.name), provided_source.get(d.name, "provided"), options,
            window, f"experiments[{e}].initial_state")
        states = oem.numeric_states(e, x0, pvecs[e])
        outputs = oem.numeric_outputs(e, states, pvecs[e])
        if not np.all(np.isfinite(states)):
            bad = int(np.flatnonzero(~np.all(np.isfinite(states), axis=0))[0])
            note = (note + "; " if note else "") + (
                f"the simulation diverged at t = {d.t[bad]:g} (sample {bad}); the model is unstable "
                "with these parameters, or the integrator needs substeps/cvodes")
        predicted = k_step_ahead(oem, e, pvecs[e], states, horizon) if horizon else None
        sims.append(Simulation(d, pvecs[e], x0, states, outputs, source, estimated, used_window,
                               predicted, horizon, note))
    return sims


def _finite_list(a: np.ndarray) -> list:
    return [float(v) if np.isfinite(v) else None for v in a]


def to_public(cm: CompiledModel, sim: Simulation) -> SimulatedExperiment:
    """The schema object of one simulation; non-finite values become null.

    Parameters
    ----------
    cm : CompiledModel
        The compiled model (names of states and outputs).
    sim : Simulation
        The numeric simulation.

    Returns
    -------
    SimulatedExperiment
        Time grid, states, outputs, initial state and its source, estimated states and window,
        horizon and predictions, and the note.
    """
    d = sim.data
    return SimulatedExperiment(
        name=d.name, time=d.t.tolist(),
        states={s: _finite_list(sim.states[i]) for i, s in enumerate(cm.states)},
        outputs={o: _finite_list(sim.outputs[j]) for j, o in enumerate(cm.outputs)},
        initial_state={s: float(sim.x0[i]) for i, s in enumerate(cm.states)},
        initial_state_source=sim.source, estimated_states=sim.estimated, estimate_window=sim.window,
        horizon=sim.horizon,
        predicted=None if sim.predicted is None else {
            o: _finite_list(sim.predicted[j]) for j, o in enumerate(cm.outputs)},
        note=sim.note)


def simulate_experiments(model: Model, parameters: dict[str, float], experiments: list[Experiment],
                         options: FitOptions, initial_states: dict[str, dict[str, float]] | None = None,
                         estimate_window: int | None = None, horizon: int | None = None,
                         ) -> list[SimulatedExperiment]:
    """Simulated states and outputs of `model` on every experiment's time grid.

    Parameters
    ----------
    model : Model
        The model; parameters missing from `parameters` keep their declared `value`.
    parameters : dict
        Values by declared name (``k``); a per-experiment estimate ``k[exp1]`` (as a FitResult
        labels it) applies to the experiment named ``exp1``.
    experiments : list of Experiment
        Inputs on a time grid; outputs are optional (needed only to estimate initial states).
    options : FitOptions
        `integrator`, `substeps` and `input_interpolation` are used, as in the fits.
    initial_states : dict, optional
        Per experiment name, states not given in the experiment's own `initial_state`.
    estimate_window : int, optional
        Leading samples on which states given neither way are estimated (least squares on the
        outputs, parameters fixed); default `default_estimate_window`.
    horizon : int, optional
        Also return k-step-ahead predictions ŷ(t | t-k) (see `k_step_ahead`).

    Returns
    -------
    list of SimulatedExperiment
        Each says where its initial state came from (`initial_state_source`).
    """
    cm = compile_model(model)
    sims = simulate_arrays(model, parameters, experiments, options, initial_states, estimate_window,
                           horizon, cm=cm)
    return [to_public(cm, s) for s in sims]


def output_metrics(cm: CompiledModel, pairs: list[tuple[np.ndarray, np.ndarray]]) -> OutputMetrics:
    """RMSE, fit % and NRMSE per output, pooled over (measured, simulated) pairs of (ny, N) arrays.

    Only samples with a finite measurement count; a non-finite simulated value there makes the
    error infinite. An output with no finite measurement is left out.

    Parameters
    ----------
    cm : CompiledModel
        The compiled model (output names).
    pairs : list of tuple of numpy.ndarray
        (measured, simulated) arrays, each of shape (ny, N).

    Returns
    -------
    OutputMetrics
        Per output: RMSE, NRMSE = ‖r‖ / ‖y − ȳ‖ (NaN for a constant measurement) and
        fit % = 100 (1 − NRMSE).
    """
    metrics = OutputMetrics()
    for j, name in enumerate(cm.outputs):
        meas = np.concatenate([m[j] for m, _ in pairs])
        sim = np.concatenate([s[j] for _, s in pairs])
        ok = np.isfinite(meas)
        if not ok.any():
            continue
        r = np.where(np.isfinite(sim[ok]), sim[ok] - meas[ok], np.inf)
        y = meas[ok]
        metrics.rmse[name] = float(np.sqrt(np.mean(r ** 2)))
        spread = float(np.linalg.norm(y - y.mean()))
        nrmse = float(np.linalg.norm(r)) / spread if spread > 0 else float("nan")
        metrics.nrmse[name] = nrmse
        metrics.fit_percent[name] = 100.0 * (1.0 - nrmse)
    return metrics


def validation_from(cm: CompiledModel, sims: list[Simulation], traces: bool = False) -> ValidationResult:
    """Per-experiment and pooled metrics of simulations against their measured outputs.

    Parameters
    ----------
    cm : CompiledModel
        The compiled model.
    sims : list of Simulation
        The simulations, each holding its experiment's measured outputs.
    traces : bool, optional
        Also return each experiment's time grid and simulated outputs.

    Returns
    -------
    ValidationResult
        Pooled RMSE, fit % and NRMSE, and per experiment the same with its initial state, its source
        and note.
    """
    per = []
    for s in sims:
        m = output_metrics(cm, [(s.data.y, s.outputs)])
        per.append(ExperimentValidation(
            name=s.data.name, rmse=m.rmse, fit_percent=m.fit_percent, nrmse=m.nrmse,
            initial_state={st: float(s.x0[i]) for i, st in enumerate(cm.states)},
            initial_state_source=s.source, estimated_states=s.estimated, estimate_window=s.window,
            note=s.note, time=s.data.t.tolist() if traces else None,
            simulated={o: _finite_list(s.outputs[j]) for j, o in enumerate(cm.outputs)} if traces else None))
    pooled = output_metrics(cm, [(s.data.y, s.outputs) for s in sims])
    return ValidationResult(rmse=pooled.rmse, fit_percent=pooled.fit_percent, nrmse=pooled.nrmse,
                            experiments=per)


def validation_metrics(model: Model, parameters: dict[str, float], experiments: list[Experiment],
                       options: FitOptions, initial_states: dict[str, dict[str, float]] | None = None,
                       estimate_window: int | None = None) -> ValidationResult:
    """Simulate every experiment and compare with its measured outputs (MATLAB compare, k = inf).

    Initial states as in `simulate_experiments`. Pooled metrics concatenate the experiments;
    `experiments` holds the per-record ones with the initial-state source. Samples used to
    estimate an initial state are included in the metrics (the window is short and reported).

    Parameters
    ----------
    model, parameters, experiments, options, initial_states, estimate_window
        As in `simulate_experiments`.

    Returns
    -------
    ValidationResult
        Pooled and per-experiment metrics (see `validation_from`).

    Raises
    ------
    DataError
        As `simulate_arrays`.
    """
    if options.input_interpolation == "cubic":   # as a fit reads them: on a finer grid, outputs unchanged
        experiments = [refine_experiment(e, DEFAULT_FACTOR) for e in experiments]
        options = refine_options(options, DEFAULT_FACTOR)
    cm = compile_model(model)
    sims = simulate_arrays(model, parameters, experiments, options, initial_states, estimate_window, cm=cm)
    return validation_from(cm, sims)


__all__ = ["simulate_experiments", "validation_metrics", "simulate_arrays", "validation_from",
           "estimate_initial_state", "k_step_ahead", "parameter_vector"]


def simulate_request(request: SimulateRequest) -> SimulateResult:
    """Simulate a model on records, with given parameters or those of a previous result.

    Parameter values and initial states are taken from the model's declared values, then from
    the previous result (`fit_result`), then from the request's own `parameters` and
    `initial_states`, each overriding the one before.

    Parameters
    ----------
    request : SimulateRequest
        The model (optional when `fit_result` is a discovery result, which carries its model),
        the records (outputs optional), and the fit's `options` (integrator and input
        interpolation), so that a simulation of a fitted model reproduces its traces.

    Returns
    -------
    SimulateResult
        States and outputs on each record's time grid, where each initial state came from,
        k-step-ahead predictions when `horizon` is set, and validation metrics for the records
        that have outputs.

    Raises
    ------
    ModelDefinitionError, DataError
        The model does not compile, or the records or parameters do not fit it; `field` names
        where the fix goes.
    """
    import time

    from greyfit.schemas.discovery import DiscoveryResult
    from greyfit.solvers.data.preprocess import prepare_request

    started = time.perf_counter()
    fit = request.fit_result.fit if isinstance(request.fit_result, DiscoveryResult) else request.fit_result
    model = request.model
    if model is None:
        carried = request.fit_result.model if request.fit_result is not None else None   # discovery's or a fit's
        if not isinstance(carried, Model):   # none (an older result), or a transfer function
            raise DataError("give the model: this fit_result carries no ODE model (results of older versions "
                            "and transfer-function fits do not)", "model")
        model = carried
    params = {k: v.value for k, v in fit.parameters.items()} if fit is not None else {}
    params.update(request.parameters)
    states = {k: dict(v) for k, v in fit.initial_states.items()} if fit is not None else {}
    names = {e.name for e in request.experiments}
    states = {k: v for k, v in states.items() if k in names}   # a previous fit may have had other records
    for name, values in request.initial_states.items():
        states.setdefault(name, {}).update(values)
    prepared, _ = prepare_request(request)   # resolves input_interpolation "auto" as the fits do
    report = fit.preprocessing if fit is not None else None
    chosen = report.substeps if report is not None else None
    if chosen and "substeps" not in request.options.model_fields_set:   # simulate as the fit integrated
        prepared = prepared.model_copy(update={"options": prepared.options.model_copy(update={"substeps": chosen})})
    # inputs read as the fit read them: cubics on a finer grid where it did (or where asked)
    factor = report.input_refinement if report is not None and report.input_refinement else None
    if "input_interpolation" in request.options.model_fields_set:
        factor = DEFAULT_FACTOR if prepared.options.input_interpolation == "cubic" else None
    if factor:
        prepared = refine_request(prepared, factor)
    cm = compile_model(model)
    sims = simulate_arrays(model, params, prepared.experiments, prepared.options, states,
                           request.estimate_window, request.horizon, cm=cm)
    measured = any(np.isfinite(s.data.y).any() for s in sims)
    used = {p.name: float(p.value) for p in model.parameters}
    used.update(params)
    public = [to_public(cm, s) for s in sims]
    return SimulateResult(parameters=used, experiments=[_thinned(e, factor) for e in public] if factor else public,
                          validation=validation_from(cm, sims) if measured else None,
                          wall_time_s=time.perf_counter() - started)


def _thinned(sim: SimulatedExperiment, factor: int) -> SimulatedExperiment:
    """A simulation on a finer grid given back on the record's own samples."""
    return sim.model_copy(update={
        "time": sim.time[::factor], "states": {k: v[::factor] for k, v in sim.states.items()},
        "outputs": {k: v[::factor] for k, v in sim.outputs.items()},
        "predicted": None if sim.predicted is None else {k: v[::factor] for k, v in sim.predicted.items()}})
