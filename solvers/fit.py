"""`fit_model`: the outline of a batch fit, top to bottom.

One attempt is a `_Fit` of the prepared request, whose `run` calls its named steps in order:
prepare (compile, arrays, extensions, layout) → build (the method's problem, from the registry in
`solvers.methods.registry`, and the checks before the solve) → solve over the starts → diagnose
(covariance, residual analysis, parameters, profiles) → assess (the quality verdict). Each step's
docstring says which of the fit's fields it sets. Around the attempts, `_fit_offline` names the
retries and ends with the review: the retries are a doubted single-shooting answer of `auto` solved
once more by multiple shooting (`_fit_chosen`; from then on the request names the method that ran),
finer substeps (`substeps_retry`) and inputs read as cubics (`cubic_retry`), each a new attempt
(`_refit`) with the CPU time left; then validation records, and review (`checks.verdict.review_fit`:
lack of fit and input handling in the verdict). What differs between methods is asked of the built
problem (`solvers.methods.batch.BatchFit`), never decided here by name.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from greyfit.schemas.fit import (
    CovariancePublic,
    ExperimentTrace,
    FitMethod,
    FitMetrics,
    FitRequest,
    FitResult,
    FitWarning,
    MethodChoice,
    ParameterEstimate,
    SolverInfo,
)
from greyfit.schemas.preprocess import PreprocessingReport
from greyfit.solvers.checks.colour import coloured_residual_warnings, negligible_fit
from greyfit.solvers.checks.diagnostics import residual_analyses
from greyfit.solvers.checks.fit_checks import (
    active_constraints,
    fastest_rate_warning,
    pre_fit_warnings,
    row_keys,
    state_peaks,
)
from greyfit.solvers.checks.input_reading import cubic_retry
from greyfit.solvers.checks.quality import QualityInputs, assess_fit
from greyfit.solvers.checks.step_choice import choose_substeps, substeps_retry
from greyfit.solvers.checks.verdict import review_fit
from greyfit.solvers.data.experiments import ExperimentData, prepare_experiments, prepared_once
from greyfit.solvers.data.preprocess import prepare_request
from greyfit.solvers.data.refine import DEFAULT_FACTOR, refine_request, thin_traces
from greyfit.solvers.dynamics.heap import keep_heap
from greyfit.solvers.errors import DataError
from greyfit.solvers.inference.covariance import CovarianceEstimate, correlation_from, estimate_covariance
from greyfit.solvers.inference.profile import check_profile_names, run_profiles
from greyfit.solvers.inference.statistics import information_criteria
from greyfit.solvers.methods.batch import BatchFit, Jacobian, Residuals
from greyfit.solvers.methods.equation_error_bias import equation_error_bias_warnings
from greyfit.solvers.methods.extensions import BatchExtensions, prepare_batch
from greyfit.solvers.methods.fixed_fit import fixed_parameter_result
from greyfit.solvers.methods.method_choice import fallback_reason, keep_better
from greyfit.solvers.methods.multistart import (
    MULTISTART_CPU_STATUS,
    draw_starts,
    multistart_agreement,
    multistart_warnings,
)
from greyfit.solvers.methods.node_initialisation import node_warnings
from greyfit.solvers.methods.registry import batch_method, online_method, simulates_outputs
from greyfit.solvers.model.carried import attach_model
from greyfit.solvers.model.compiler import CompiledModel, compile_model, guard_notes
from greyfit.solvers.model.parameters import ParameterLayout, build_layout
from greyfit.solvers.nlp.solver import NlpOutcome
from greyfit.solvers.simulation.validate import validate_fit
from greyfit.solvers.timing import stage, timed_fit

__all__ = ["fit_model", "draw_starts", "Residuals"]

BOUND_TOLERANCE = 1e-5


def _at_bound(layout: ParameterLayout, theta_s: np.ndarray) -> list[Literal["lower", "upper"] | None]:
    lo, hi = layout.lower / layout.scale, layout.upper / layout.scale
    flags: list[Literal["lower", "upper"] | None] = []
    for i, v in enumerate(theta_s):
        if np.isfinite(lo[i]) and v - lo[i] <= BOUND_TOLERANCE * max(1.0, abs(lo[i])):
            flags.append("lower")
        elif np.isfinite(hi[i]) and hi[i] - v <= BOUND_TOLERANCE * max(1.0, abs(hi[i])):
            flags.append("upper")
        else:
            flags.append(None)
    return flags


def fit_model(request: FitRequest) -> FitResult:
    """Fit the request's model to its experiments.

    Parameters
    ----------
    request : FitRequest
        The model, the experiments, the method and its options.

    Returns
    -------
    FitResult
        Estimates with covariance, metrics, residual analysis and the quality verdict (see
        `greyfit.schemas.fit.FitResult`). Online estimators go their own way; otherwise each
        experiment's `preprocess` is applied first and `validation` records are simulated after.

    Raises
    ------
    ModelDefinitionError
        When the model cannot be compiled (syntax, unknown names, missing equations).
    DataError
        When the experiments do not fit the model or the options name an unknown output; the
        error's `field` names where the fix goes.
    """
    keep_heap()   # once per process: a fit's arrays reuse the last fit's pages (docs/deployment.md)
    online = online_method(request.method)
    with timed_fit() as watch:
        if online is not None:
            with stage("solve"):
                result = attach_model(online.fit(request), request.model)
        else:
            with prepared_once():   # the solve, the checks and the screen share the records' arrays
                result = _fit_offline(request)
    result.solver.timings = watch.report()
    return result


def _fit_offline(request: FitRequest) -> FitResult:
    """The attempts and what follows them, in order: prepare the request (preprocessing, substeps,
    the input reading) → the first attempt (`_fit_chosen`: multiple shooting once more after a doubted
    single-shooting answer of auto) → the substeps retry (`substeps_retry`) → the cubic-input retry
    (`cubic_retry`), each retry a new attempt with the CPU time left (`_refit`) → validation records
    → review (`review_fit`: lack of fit and input handling in the verdict)."""
    cpu0, started = time.process_time(), time.perf_counter()
    with stage("prepare"):
        prepared, preprocessing = read_cubic_inputs(*choose_substeps(*prepare_request(request)))
    result = _fit_chosen(prepared, cpu0)
    # from here on the request names the method that ran: the checks after the fit ask it
    prepared = prepared.model_copy(update={"method": result.solver.method})
    with stage("checks_after"):
        retry = substeps_retry(prepared, result.model_copy(update={"preprocessing": preprocessing}))
    retry = _with_cpu_left(retry, request.options.max_cpu_time - (time.process_time() - cpu0))
    if retry is not None:   # the chosen substeps proved coarse at the estimates: once more, finer
        (prepared, preprocessing), result = retry, _refit(retry[0], result)
        result.solver.wall_time_s = time.perf_counter() - started   # the user waited for both
    given = "substeps" in request.options.model_fields_set
    with stage("checks_after"):
        retry, late = cubic_retry(prepared, result, preprocessing, given)
    retry = _with_cpu_left(retry, request.options.max_cpu_time - (time.process_time() - cpu0))
    if retry is not None:   # smooth inputs read as ramps moved the estimates: once more, read as cubics
        (prepared, preprocessing), result = retry, _refit(retry[0], result)
        result.solver.wall_time_s = time.perf_counter() - started
    if prepared.validation:
        with stage("validation"):
            result.validation = validate_fit(prepared, result)
    result.preprocessing = preprocessing
    if preprocessing is not None and preprocessing.input_refinement:
        thin_traces(result, preprocessing.input_refinement)
    # lack of fit and input handling in the verdict; units and the model travel with the result
    with stage("checks_after"):
        result = review_fit(prepared, result, late)
    return attach_model(result, request.model)


def _with_cpu_left(retry, left: float):
    """A retry (request, report) given the CPU time the fit has left, or None when none is left:
    `max_cpu_time` is the whole fit's, and each retry used to get all of it again (a fit of two
    coupled tanks with `max_cpu_time` 20 spent 42 s of CPU in two attempts)."""
    if retry is None or left <= 0:
        return None
    request, report = retry
    return request.model_copy(update={"options": request.options.model_copy(update={"max_cpu_time": left})}), report


def _refit(request: FitRequest, first: FitResult) -> FitResult:
    """`_fit_prepared` of a retry, keeping the first fit's method choice (the retry names the method)."""
    choice = first.solver.method_choice
    result = _fit_prepared(request)
    result.solver.method_choice = choice
    return result


def read_cubic_inputs(request: FitRequest, report: PreprocessingReport | None):
    """`input_interpolation: cubic` made concrete: an output-error fit runs on the records' finer grid
    (`refine_request`); equation error reads the inputs through its derivative filter, as linear.

    Parameters
    ----------
    request : FitRequest
        The prepared request (substeps chosen).
    report : PreprocessingReport or None
        Its preprocessing report.

    Returns
    -------
    request : FitRequest
        The request to fit: refined, or with ``foh``; itself unless the interpolation is ``cubic``.
    report : PreprocessingReport or None
        The report, with `input_refinement` (or a note) added.
    """
    if request.options.input_interpolation != "cubic":
        return request, report
    report = report or PreprocessingReport()
    if not simulates_outputs(request.method) or request.model.discrete is not None:
        options = request.options.model_copy(update={"input_interpolation": "foh"})
        note = "equation error and difference equations read the inputs at the samples: cubic is taken as linear"
        return request.model_copy(update={"options": options}), report.model_copy(update={
            "input_interpolation": {n: "foh" for n in report.input_interpolation}, "interpolation_note": note})
    return refine_request(request, DEFAULT_FACTOR), report.model_copy(update={"input_refinement": DEFAULT_FACTOR})


def _fit_chosen(request: FitRequest, cpu0: float) -> FitResult:
    """`_fit_prepared`; where auto chose single shooting and its answer is doubtful, multiple shooting
    once more with the CPU time left (of the whole fit, begun at process time `cpu0`), and the better
    answer (`method_choice.keep_better`)."""
    started = time.perf_counter()
    result = _fit_prepared(request)
    choice = result.solver.method_choice
    solved = choice is not None and choice.ran == FitMethod.single_shooting and result.solver.starts > 0
    why = fallback_reason(result) if solved else ""
    if choice is None or not why:
        return result
    left = request.options.max_cpu_time - (time.process_time() - cpu0)
    if left <= 0:
        choice.reason += f"; {why}, and no CPU time is left (options.max_cpu_time) to try multiple shooting"
        return result
    multiple = request.model_copy(update={"method": FitMethod.multiple_shooting, "options": request.options.model_copy(
        update={"max_cpu_time": left})})
    kept = keep_better(result, _fit_prepared(multiple), why)
    kept.solver.wall_time_s = time.perf_counter() - started   # the user waited for both
    return kept


def _fit_prepared(request: FitRequest) -> FitResult:
    """One attempt at the prepared request: `_Fit(request).run()`. What a retry reruns."""
    return _Fit(request).run()


@dataclass
class _Fit:
    """One batch fit of a prepared request, as named steps that share its state (in the manner of
    scikit-learn's `NewtonSolver`): each step's docstring says what it sets, `run` calls them in
    order. A retry (finer substeps, inputs read as cubics, multiple shooting after a doubted
    single-shooting answer) is a new `_Fit` of the retried request, run again (`_fit_prepared`)."""

    request: FitRequest
    started: float = field(default_factory=time.perf_counter)
    cpu0: float = field(default_factory=time.process_time)
    # set by `prepare`
    cm: CompiledModel = field(init=False)
    data: list[ExperimentData] = field(init=False)
    ext: BatchExtensions = field(init=False)
    layout: ParameterLayout = field(init=False)
    starts: list[np.ndarray] = field(init=False)
    # set by `build`
    built: BatchFit = field(init=False)
    before: list[FitWarning] = field(init=False)   # the pre-fit warnings; `diagnose` adds to them
    # set by `solve`
    outcome: NlpOutcome = field(init=False)
    n_starts: int = field(init=False)
    compiled: bool | None = field(init=False)
    # set by `diagnose`
    theta: np.ndarray = field(init=False)          # the physical free parameters at the estimates
    bounds: list[Literal["lower", "upper"] | None] = field(init=False)
    x0s: list = field(init=False)                  # per experiment, state -> initial value
    jacobian: Jacobian = field(init=False)         # at the estimates
    free: np.ndarray = field(init=False)           # which of its columns are free (not at a bound)
    cost: float = field(init=False)
    ndata: int = field(init=False)
    nvarys: int = field(init=False)
    channels: Residuals = field(init=False)
    analyses: list = field(init=False)             # residual analyses, one per channel
    covariance: CovarianceEstimate = field(init=False)
    result: FitResult = field(init=False)          # the result before its verdict

    def run(self) -> FitResult:
        """prepare → build → solve → diagnose → assess; a request with nothing to estimate ends at
        prepare, reported like a fit (one simulation)."""
        fixed = self.prepare()
        if fixed is not None:
            return fixed
        self.build()
        self.solve()
        self.diagnose()
        return self.assess()

    def prepare(self) -> FitResult | None:
        """Compile the model, read the records, apply the batch extensions and lay out the free
        parameters. Sets `cm`, `data`, `ext`, `layout` and `starts`; returns the fixed-parameter
        result when there is nothing to estimate, else None."""
        request, opts = self.request, self.request.options
        with stage("prepare"):
            cm = compile_model(request.model)
            data = prepare_experiments(request.experiments, cm)
            self.ext = prepare_batch(request, cm, data)   # discrete-time checks, prefilter, time-varying parameters
            self.cm, self.data = self.ext.cm, self.ext.data
            self.layout = build_layout(self.ext.model, [d.name for d in self.data])
            if self.layout.size == 0:   # nothing to estimate: a simulation, reported like a fit
                return _fixed_parameters(request, self.cm, self.data, self.layout, self.started)
            unknown_w = sorted(set(opts.output_weights) - set(self.cm.outputs))
            if unknown_w:
                raise DataError(f"'{unknown_w[0]}' is not an output (outputs: {self.cm.outputs})",
                                f"options.output_weights.{unknown_w[0]}")
            self.starts = draw_starts(self.layout, opts.multistart, opts.seed)
            check_profile_names(opts.profile, list(self.layout.labels))
        return None

    def build(self) -> None:
        """The method's problem from the registry (for auto, the method choice), the extensions
        attached to it, then the checks before the solve. Sets `built` and `before`."""
        opts = self.request.options
        with stage("prepare"):
            built = batch_method(self.request.method).build(self.cm, self.data, self.layout, opts)
            self.ext.attach(built.problem, self.layout)
            if built.eep is not None:
                built.affine_solve = self.ext.solve_affine
            self.built = built
        with stage("checks_before"):
            self.before = pre_fit_warnings(self.cm, self.data, self.layout, opts, built.problem, built.eep,
                                           built.oem) + guard_notes(self.cm)

    def solve(self) -> None:
        """Solve over the starts. Sets `outcome`, `n_starts` and `compiled`."""
        with stage("solve"):
            self.outcome, self.n_starts, self.compiled = self.built.solve(self.starts, self.request.options,
                                                                          self.cpu0)

    def diagnose(self) -> None:
        """Estimates, the Jacobian at them, residual analyses, the covariance, the warnings these raise,
        and the result before its verdict (profiles and the extensions' share included). Sets `theta`,
        `bounds`, `x0s`, `jacobian`, `free`, `cost`, `ndata`, `nvarys`, `channels`, `analyses`,
        `covariance` and `result`; adds to `before`."""
        with stage("diagnostics"):
            self._estimates()
            self._covariance()
            self.result = self._draft_result()
            self._finish_result()

    def _estimates(self) -> None:
        """Sets `theta`, `bounds`, `x0s`, `jacobian`, `free`, `ndata`, `nvarys`, `cost`, `channels`, `analyses`."""
        opts, built, layout, outcome = self.request.options, self.built, self.layout, self.outcome
        if not np.all(np.isfinite(outcome.w)):   # report the start rather than NaN estimates
            outcome.w, outcome.success = built.problem.initial_guess(layout.initial), False
        theta_s = outcome.w[:layout.size]
        self.theta = layout.physical(theta_s)
        self.bounds = _at_bound(layout, theta_s)
        self.x0s = built.problem.x0_of(outcome.w)
        # at the point the result reports, as its checks read it back (value / scale, an ulp from the
        # solver's): the input reading and the lack-of-fit screen then find this Jacobian, not compute theirs
        jp = self.jacobian = built.jacobian(self.theta / layout.scale, outcome.w, self.x0s)
        self.free = np.array([b is None for b in self.bounds] + [True] * jp.n_extra)
        if built.eep is not None:   # noise in the regressors biases equation error: an instrumental-variable check
            self.before = self.before + equation_error_bias_warnings(built.eep, self.cm, self.data, layout,
                                                                     outcome.w, self.free[:layout.size], opts)
        self.ndata, self.nvarys = jp.res.size, int(self.free.sum())
        self.cost = 0.5 * float(jp.res @ jp.res)
        self.channels = built.channels(self.theta, self.x0s, jp.res)
        self.analyses = residual_analyses(self.channels.channels, _segments(self.cm, self.data, self.channels))

    def _covariance(self) -> None:
        """Sets `covariance` (robust where the residual is not white); adds the coloured-residual warnings."""
        opts, built, jp, keep = self.request.options, self.built, self.jacobian, self.free
        white = all(a.whiteness.passed or not a.whiteness.lags for a in self.analyses)
        robust = opts.robust_covariance == "always" or (opts.robust_covariance == "auto" and not white)
        sample_keys, experiment_keys = row_keys(self.data, built.eep, self.cm)
        cov = self.covariance = estimate_covariance(
            jp.jac, jp.res, jp.labels, jp.values, jp.scale, keep, self.layout.size, opts.confidence_level,
            groups=jp.groups, sample_keys=sample_keys, experiment_keys=experiment_keys, robust=robust)
        if built.oem is not None and self.cm.model.discrete is None and not negligible_fit(self.analyses):
            # output error of an ODE: coloured noise or a model error? (not on noise-free data, whose residual
            # is the integrator's own error; not on a difference equation, whose noise model is the user's)
            self.before = self.before + coloured_residual_warnings(
                jp.jac, jp.res, jp.groups, keep, jp.labels, self.layout.size, sample_keys, experiment_keys, cov)

    def _finish_result(self) -> None:
        """Active constraints, the multistart's agreement, profiles and the extensions' share of `result`."""
        opts, layout, result = self.request.options, self.layout, self.result
        agree = multistart_agreement(self.built.run, layout, self.ndata, self.nvarys, opts.confidence_level)
        self.before = self.before + multistart_warnings(self.built.run, agree)   # multiple_optima: not `good`
        result.active_constraints = active_constraints(self.cm, layout, self.outcome.w[:layout.size])
        if agree is not None:
            result.solver.starts_at_best = agree.starts_at_best
            result.alternative_optima = agree.optima or None
        result.profile = run_profiles(self.built.problem, opts, self.outcome, layout, self.ndata, self.nvarys,
                                      self.covariance)
        self.result = self.ext.finish(result, layout, self.theta, self.covariance)

    def assess(self) -> FitResult:
        """The quality verdict on `result` (`checks.quality.assess_fit`), from what its checks read of
        the fit (`_quality_inputs`). Returns the assessed result."""
        with stage("checks_after"):
            return assess_fit(self.result, self._quality_inputs())

    def _draft_result(self) -> FitResult:
        """The `FitResult` of the solved fit, before the checks."""
        opts, layout, cov, channels, outcome = (self.request.options, self.layout, self.covariance,
                                                self.channels, self.outcome)
        params: dict[str, ParameterEstimate] = {}
        for i, label in enumerate(layout.labels):
            params[label] = ParameterEstimate(
                value=float(self.theta[i]), stderr=cov.stderr.get(label), ci95=cov.ci.get(label),
                at_bound=self.bounds[i], initial=float(layout.initial[i]), experiment=layout.experiment[i],
                stderr_classical=cov.classical_stderr.get(label, cov.stderr.get(label)))
        for name, value in layout.fixed.items():
            params[name] = ParameterEstimate(value=value, fixed=True, initial=value)
        covariance = correlation = None
        if cov.matrix is not None:
            covariance = CovariancePublic(names=cov.names, matrix=cov.matrix.tolist())
            correlation = CovariancePublic(names=cov.names, matrix=correlation_from(cov.matrix).tolist())
        traces = None
        if opts.return_traces:
            traces = [ExperimentTrace(
                name=d.name, time=d.t.tolist(),
                simulated={ch: (meas[c] + r[c]).tolist() for c, ch in enumerate(channels.channels)},
                residuals={ch: [None if not np.isfinite(v) else float(v) for v in r[c]]
                           for c, ch in enumerate(channels.channels)})
                for d, (meas, r) in zip(self.built.data, channels.per_experiment)]
        cost, ndata, nvarys, analyses, built = self.cost, self.ndata, self.nvarys, self.analyses, self.built
        aic, bic = information_criteria(2 * cost, ndata, nvarys)
        return FitResult(
            success=outcome.success, status="success" if outcome.success else "failed",
            message=_message(outcome.status), parameters=params, confidence_level=opts.confidence_level,
            covariance=covariance, covariance_note=cov.note, correlation=correlation,
            initial_states=built.initial_states(self.x0s),
            metrics=FitMetrics(cost=cost, ndata=ndata, nfree=ndata - nvarys, nvarys=nvarys,
                               rmse={a.output: a.rmse for a in analyses},
                               fit_percent={a.output: a.fit_percent for a in analyses}, aic=aic, bic=bic),
            solver=SolverInfo(method=built.method, method_choice=built.choice, iterations=outcome.iterations,
                              wall_time_s=time.perf_counter() - self.started, return_status=outcome.status,
                              starts=self.n_starts, compiled=self.compiled, **built.solver_details()),
            residual_analysis=analyses, traces=traces,
            covariance_classical=None if cov.classical is None else CovariancePublic(
                names=cov.names, matrix=cov.classical.tolist()))

    def _quality_inputs(self) -> QualityInputs:
        """Collect what `solvers.quality` checks; state sizes and step size only for output error."""
        layout, oem, channels, result, outcome = (self.layout, self.built.oem, self.channels, self.result,
                                                  self.outcome)
        # parameter columns, rescaled to a 100 % change of the estimate (at least of its initial scale)
        jp = self.jacobian
        size = np.maximum(np.abs(jp.values) / jp.scale, 1.0)
        keep = self.free & (np.arange(self.free.size) < layout.size)
        fitted = guess = None
        before = self.before
        if oem is not None and channels.states is not None:
            fitted, guess = state_peaks(oem, channels.states, layout.initial)
            before = before + fastest_rate_warning(oem.cm, oem.data, layout, outcome.w[:layout.size],
                                                   channels.states, self.request.options)
        failures = list(oem.simulation_failures) if oem is not None else []
        before = before + node_warnings(oem)
        signed = {lab for i, lab in enumerate(layout.labels)
                  if layout.lower[i] >= 0 or layout.upper[i] <= 0}
        return QualityInputs(
            converged=outcome.success, status=outcome.status, cost=result.metrics.cost if
            result.metrics.cost is not None else float("nan"), nlp_cost=outcome.cost,
            method=result.solver.method.value, covariance=self.covariance, jac=(jp.jac * size)[:, keep],
            jac_labels=[lab for lab, k in zip(jp.labels, keep) if k],
            measured={ch: [m[c] for m, _ in channels.per_experiment] for c, ch in enumerate(channels.channels)},
            fitted_state_peak=fitted, guess_state_peak=guess, state_names=list(self.request.model.states),
            simulation_failures=failures, before=before, active_constraints=result.active_constraints,
            sign_constrained=signed)


def _fixed_parameters(request: FitRequest, cm, data, layout: ParameterLayout, started: float) -> FitResult:
    if request.method != FitMethod.auto:
        return fixed_parameter_result(request, cm, data, layout, started)
    single = request.model_copy(update={"method": FitMethod.single_shooting})
    result = fixed_parameter_result(single, cm, data, layout, started)
    result.solver.method_choice = MethodChoice(
        requested=FitMethod.auto, ran=FitMethod.single_shooting,
        reason="no free parameter: one simulation from the initial states is the whole fit")
    return result


def _segments(cm, data, channels: Residuals) -> list[list[tuple]]:
    """Per channel, per record: (measured, residual, inputs) on the samples where both are finite."""
    segments: list[list[tuple]] = []
    for c, _ in enumerate(channels.channels):
        segments.append([])
        for d, (meas, r) in zip(data, channels.per_experiment):
            ok = np.isfinite(meas[c]) & np.isfinite(r[c])
            segments[-1].append((meas[c][ok], r[c][ok], {u: d.u[k][ok] for k, u in enumerate(cm.inputs)}))
    return segments


def _message(status: str) -> str:
    return {
        "Solve_Succeeded": "Ipopt converged to the requested tolerance",
        "Solved_To_Acceptable_Level": "Ipopt converged to an acceptable level",
        "Linear_Least_Squares": "solved in closed form (residual affine in the parameters, no active bound)",
        "Maximum_Iterations_Exceeded": "Ipopt stopped at max_iter; raise options.max_iter or improve the guess",
        "Maximum_CpuTime_Exceeded": "Ipopt stopped at max_cpu_time; raise options.max_cpu_time",
        MULTISTART_CPU_STATUS: "max_cpu_time ran out before every start ran; the best start so far is "
                               "reported, not the multistart's answer; raise options.max_cpu_time or "
                               "lower options.multistart",
        "Infeasible_Problem_Detected": "the bounds and constraints cannot all hold",
    }.get(status, f"Ipopt returned {status}")
