"""Experiment design: the input that shrinks the parameters' intervals (D, A, E) or separates rival models (T).

`design_experiment(request)` reads top to bottom: lay out the design (model, parameters, grid,
signal) -> starting signals -> solve the criterion's NLP -> predict what the design and the
baseline give -> the result.
"""
from __future__ import annotations

import math
import time as clock
from typing import Optional

import numpy as np

from greyfit.schemas.design import DesignRequest, DesignResult, Discrimination, PredictedParameter
from greyfit.schemas.experiment import Experiment
from greyfit.solvers.design.criteria import SETTLE_PROBABILITY, divergence_to_settle, settle_probability
from greyfit.solvers.design.discrimination import (
    Pair,
    PairFit,
    fit_pairs,
    rival_pairs,
    solve_discrimination_design,
)
from greyfit.solvers.design.information import (
    check_identifiable,
    check_seen,
    exact_criterion,
    solve_information_design,
    stderrs,
)
from greyfit.solvers.design.setup import (
    DesignSetup,
    baseline_inputs,
    baseline_time,
    design_setup,
    initial_state,
)
from greyfit.solvers.errors import DataError, FitError

__all__ = ["design_experiment"]


def _starts(setup: DesignSetup, request: DesignRequest, rng: np.random.Generator) -> list[np.ndarray]:
    starts = []
    if request.baseline is not None:
        U = _baseline_on_grid(setup, request)
        if U is not None:
            starts.append(setup.signal.project(U))
    while len(starts) < request.options.starts:
        starts.append(setup.signal.start(rng))
    return starts


def _baseline_on_grid(setup: DesignSetup, request: DesignRequest) -> Optional[np.ndarray]:
    """The baseline's inputs held onto the design's samples (None where the grids do not overlap)."""
    assert request.baseline is not None
    tb = baseline_time(request.baseline)
    Ub = baseline_inputs(request, setup.model.cm.inputs, request.baseline)
    if tb[0] > setup.time[-1] or tb[-1] < setup.time[0]:
        return None
    idx = np.clip(np.searchsorted(tb, setup.time, side="right") - 1, 0, len(tb) - 1)
    return Ub[:, idx]


def _experiment(setup: DesignSetup, request: DesignRequest, U: np.ndarray) -> Experiment:
    cm = setup.model.cm
    return Experiment(name="designed", time=[float(t) for t in setup.time],
                      inputs={name: [float(v) for v in U[i]] for i, name in enumerate(cm.inputs)},
                      initial_state={name: float(setup.x0[i]) for i, name in enumerate(cm.states)})


def _baseline_grid(setup: DesignSetup, request: DesignRequest):
    if request.baseline is None:
        return None
    base = request.baseline
    x0 = initial_state(setup.model.cm, {**request.initial_state, **base.initial_state}, "baseline.initial_state")
    return baseline_time(base), baseline_inputs(request, setup.model.cm.inputs, base), x0


def _information_result(setup: DesignSetup, request: DesignRequest, rng: np.random.Generator) -> dict:
    check_seen(setup, setup.signal.inputs(setup.signal.start(np.random.default_rng(request.options.seed))),
               request.options.substeps)
    solved = solve_information_design(setup, request, _starts(setup, request, rng), rng)
    U = setup.signal.inputs(solved.z)
    check_identifiable(setup, U, request.options.substeps)
    se = stderrs(setup, U, setup.time, setup.x0, request.options.substeps)
    base = _baseline_grid(setup, request)
    se_b, objective_b = None, None
    if base is not None:
        tb, Ub, xb = base
        se_b = stderrs(setup, Ub, tb, xb, request.options.substeps)
        objective_b = exact_criterion(setup, request, Ub, tb, xb)
    names, values = setup.model.free_names, setup.model.p[list(setup.model.free)]
    params = {names[i]: PredictedParameter(
        value=float(values[i]), stderr=None if se is None else float(se[i]),
        stderr_baseline=None if se_b is None else float(se_b[i])) for i in setup.interest}
    improvement = None
    if se is not None and se_b is not None:
        improvement = float(np.exp(np.mean([math.log(se_b[i] / se[i]) for i in setup.interest])))
    return dict(experiment=_experiment(setup, request, U), objective=solved.objective,
                objective_baseline=objective_b, parameters=params, improvement=improvement,
                status=solved.status, iterations=solved.iterations)


def _to_settle(divergence: float, penalty: float, duration: float) -> tuple[float, Optional[float]]:
    """The pair's chance to be settled, and the duration that would make it 0.9 (None if it is)."""
    p = settle_probability(divergence, penalty)
    if p >= SETTLE_PROBABILITY:
        return p, None
    needed = divergence_to_settle(penalty)
    return p, duration * needed / max(divergence, 1e-12)


def _discrimination_rows(pairs: list[Pair], fits: list[PairFit], base_fits: Optional[list[PairFit]],
                         n_values: int, n_base: Optional[int], duration: float) -> list[Discrimination]:
    rows = []
    for k, (pair, fit) in enumerate(zip(pairs, fits)):
        extra = len(pair.rival.free) - len(pair.truth.free)
        base = base_fits[k] if base_fits is not None else None
        settle, to_settle = _to_settle(fit.divergence, extra * math.log(n_values), duration)
        rows.append(Discrimination(
            settle_probability=settle, duration_to_settle=to_settle,
            rival=pair.rival.name, truth=pair.truth.name, divergence=fit.divergence,
            divergence_baseline=None if base is None else base.divergence,
            expected_delta_bic=fit.divergence + extra * math.log(n_values),
            expected_delta_bic_baseline=None if base is None or n_base is None
            else base.divergence + extra * math.log(n_base),
            rival_parameters={pair.rival.cm.parameters[i]: float(fit.rival_p[i]) for i in pair.rival.free}))
    return rows


def _discrimination_result(setup: DesignSetup, request: DesignRequest, rng: np.random.Generator) -> dict:
    pairs = rival_pairs(setup, request)
    kept = solve_discrimination_design(setup, request, _starts(setup, request, rng), pairs)
    U = setup.signal.inputs(kept.z)
    base_fits, n_base, objective_b, improvement = None, None, None, None
    if request.baseline is not None:
        tb, Ub, _ = _baseline_grid(setup, request)
        base_fits = fit_pairs(pairs, setup.model, Ub, tb, request)
        n_base = len(tb) * len(request.outputs)
        objective_b = -min(f.divergence for f in base_fits)
        improvement = kept.smallest / max(-objective_b, 1e-300)
    rows = _discrimination_rows(pairs, kept.fits, base_fits, len(setup.time) * len(request.outputs), n_base,
                                float(setup.time[-1] - setup.time[0]))
    return dict(experiment=_experiment(setup, request, U), objective=-kept.smallest,
                objective_baseline=objective_b, discrimination=rows, improvement=improvement,
                status=kept.status, iterations=kept.iterations)


def design_experiment(request: DesignRequest) -> DesignResult:
    """Design the input of the next experiment.

    Parameters
    ----------
    request : DesignRequest
        The model (or a fit result), the input's limits, the measured outputs, the criterion.

    Returns
    -------
    DesignResult
        The designed experiment, its criterion and predicted standard errors (or discrimination)
        beside the baseline's.

    Raises
    ------
    ModelDefinitionError, DataError
        A request that cannot be designed for, naming the field to fix.
    """
    started = clock.perf_counter()
    rng = np.random.default_rng(request.options.seed)
    setup = design_setup(request)
    try:
        with np.errstate(over="raise", invalid="ignore", divide="ignore"):
            if request.criterion == "T":
                fields = _discrimination_result(setup, request, rng)
            else:
                fields = _information_result(setup, request, rng)
    except (RuntimeError, ValueError, FloatingPointError, OverflowError, np.linalg.LinAlgError) as exc:
        if isinstance(exc, FitError):
            raise
        # CasADi and numpy fail this way on limits and values no simulation survives (an input of 1e300,
        # a hold of a nanosecond over hours): the request's numbers, not a server fault
        raise DataError(f"the design could not be computed with these limits and values ({type(exc).__name__}: "
                        f"{str(exc).splitlines()[0][:200] if str(exc) else 'no message'}); check the inputs' "
                        "limits, the duration and sample time, and the parameters' values", "inputs") from exc
    notes = ["the initial state is taken as known; the noise as white with the given standard deviations"]
    if request.robust_draws:
        notes.append(f"the criterion is averaged over the estimates and {request.robust_draws} draws from the "
                     "covariance")
    return DesignResult(criterion=request.criterion, notes=notes,
                        wall_time_s=clock.perf_counter() - started, **fields)
