"""Solid ground first: the loop does not screen from a base fit it has reason to distrust.

Two cases the fit itself flags:

- `integration_step_coarse`: RK4 at the requested substeps is inaccurate (or unstable) on the
  fitted model's fastest mode. On a coarsely sampled record the fit can even create that mode
  (a slow lag collapsed below the sample time turns, at one RK4 step, into an artificial mode that
  mimics a delay), and every screen from it points at the integrator. The fit is repeated with the
  substeps the warning suggests (at least twice as many), until the warning
  goes or the substeps reach their limit; the finer setting is kept for the whole search. The refit
  starts from the declared values when |λ|h was beyond RK4's stability limit (the mode may be the
  integrator's artefact), else from the base fit's estimates (only its accuracy was in doubt).
- `suspect` with the sign of a local minimum (`fit_below_noise_level`: the residual far above the
  data's own noise level): a multistart from the declared start and draws inside the bounds, bounded
  by its number of starts and iterations per start (at most `MULTISTART_ITER_FACTOR` times the base
  fit's, at least `MULTISTART_MIN_ITER`), so its answer does not depend on machine load;
  the best is kept when better. The CPU limit (`MULTISTART_CPU_FACTOR` times the base fit's CPU
  time, at least `MULTISTART_CPU_FLOOR_S`, and at most the request's `max_cpu_time` and what is left
  of the discovery budget) is a safety net: a multistart it cuts off is not an answer, the base fit
  is kept and the note says the limit ended it. Bounded by the whole budget alone, a 3-state motor's
  multistart ran for 300 CPU-s before the first screen.
"""
from __future__ import annotations

import numpy as np

from greyfit.schemas.fit import FitRequest, FitResult
from greyfit.solvers.discovery.budget import Clock
from greyfit.solvers.discovery.confirm import with_estimates
from greyfit.solvers.errors import FitError
from greyfit.solvers.fit import fit_model
from greyfit.solvers.methods.multistart import CPU_STATUSES

MAX_SUBSTEPS = 100          # FitOptions.substeps' limit
RK4_STABILITY_LIMIT = 2.78  # |λ|h where RK4 stops being stable on a real mode
REFINE_ROUNDS = 2
# the residual far above the data's own noise level: a local minimum, or much missing physics (a
# residual that is merely not white is the usual sign of a missing term, and no reason to restart)
LOCAL_MINIMUM_CODES = {"fit_below_noise_level"}
MULTISTART_STARTS = 8
MULTISTART_MAX_ITER = 100   # per start ...
MULTISTART_ITER_FACTOR = 3  # ... and at most this many times the base fit's iterations
MULTISTART_MIN_ITER = 30
MULTISTART_CPU_FACTOR = 20.0  # the safety net: 8 starts at up to 2.5 base fits each (a start far off costs more)
MULTISTART_CPU_FLOOR_S = 10.0


def solid_ground(fit_req: FitRequest, base: FitResult, clock: Clock,
                 base_cpu_s: float = 0.0) -> tuple[FitRequest, FitResult, list[str]]:
    """(request, base fit, notes): the base fit refitted with finer steps and/or a multistart when it
    warns as above; unchanged otherwise. Timed as the base fit.

    Parameters
    ----------
    fit_req : FitRequest
        The base fit's request.
    base : FitResult
        The base fit.
    clock : Clock
        The discovery budget (the multistart is skipped once it is spent; what is left caps its CPU
        time as a safety net).
    base_cpu_s : float
        CPU seconds of the base fit: the multistart's CPU safety net is a multiple of it.

    Returns
    -------
    tuple of (FitRequest, FitResult, list of str)
        The request the search goes on with (finer `options.substeps` where they were raised), the base
        fit it starts from, and notes saying what was refitted and why.
    """
    notes: list[str] = []
    fit_req = with_resolved_substeps(fit_req, base)
    with clock.phase("base_fit"):
        fit_req, base = _finer_steps(fit_req, base, notes)
        if clock.allows():
            base = _multistart(fit_req, base, clock, notes, base_cpu_s)
    return fit_req, base, notes


def with_resolved_substeps(fit_req: FitRequest, base: FitResult) -> FitRequest:
    """The request with the RK4 substeps the base fit chose for itself made explicit.

    A fit not given `options.substeps` chooses them from the model's fastest mode
    (`preprocessing.substeps`); the request still says 1. The screens linearise and simulate with
    the request's options, so they would integrate at one step what the fit integrated at several,
    and every refit would choose again (and sometimes fit twice, `substeps_retry`). Made explicit,
    the screens see the trajectory the fit saw, and a refit that needs more gets them from
    `confirm.refit_options` or the fit's own `integration_step_coarse` warning.

    Parameters
    ----------
    fit_req : FitRequest
        The base fit's request.
    base : FitResult
        The base fit.

    Returns
    -------
    FitRequest
        `fit_req` with `options.substeps` set to the base fit's choice; unchanged when the request gave
        them, or the fit chose none.
    """
    chosen = base.preprocessing.substeps if base.preprocessing is not None else None
    if chosen is None or "substeps" in fit_req.options.model_fields_set:
        return fit_req
    return fit_req.model_copy(update={"options": fit_req.options.model_copy(update={"substeps": int(chosen)})})


def _coarse(fit: FitResult):
    return next((w for w in fit.warnings if w.code == "integration_step_coarse"), None)


def _finer_steps(fit_req: FitRequest, base: FitResult, notes: list[str]) -> tuple[FitRequest, FitResult]:
    for _ in range(REFINE_ROUNDS):
        warning = _coarse(base)
        substeps = fit_req.options.substeps
        if warning is None or substeps >= MAX_SUBSTEPS:
            break
        need = int(warning.detail.get("suggested_substeps", 2 * substeps))
        finer = min(MAX_SUBSTEPS, max(need, 2 * substeps))
        # beyond RK4's stability limit the fitted mode may be the integrator's own artefact: start
        # again from the declared values; inside it the fit is only inaccurate: start from it
        unstable = float(warning.detail.get("max_rate", np.inf)) * float(warning.detail.get("step", 0)) \
            >= RK4_STABILITY_LIMIT
        model = fit_req.model if unstable else with_estimates(fit_req.model, base)
        req = fit_req.model_copy(update={"model": model,
                                         "options": fit_req.options.model_copy(update={"substeps": finer})})
        try:
            refit = fit_model(req)
        except (FitError, RuntimeError, ValueError) as exc:
            notes.append(f"the base fit warned integration_step_coarse; a refit at options.substeps = {finer} "
                         f"failed ({exc}); screened at {substeps}")
            break
        if refit.quality == "failed":
            notes.append(f"the base fit warned integration_step_coarse; the refit at options.substeps = {finer} "
                         f"failed ({refit.solver.return_status}); screened at {substeps}")
            break
        start = "the declared start" if unstable else "its estimates"
        notes.append(f"the base fit warned integration_step_coarse at options.substeps = {substeps} "
                     f"({warning.message}); it was refitted from {start} at substeps = {finer}, "
                     "which the whole search then uses")
        fit_req, base = req.model_copy(update={"model": fit_req.model}), refit
    return fit_req, base


def multistart_bounds(fit_req: FitRequest, base: FitResult, clock: Clock, base_cpu_s: float) -> tuple[float, int]:
    """(CPU seconds, iterations per start) of the solid-ground multistart, relative to the base fit.

    Parameters
    ----------
    fit_req : FitRequest
        The base fit's request (its `max_cpu_time` and `max_iter` bound both).
    base : FitResult
        The base fit (its iterations).
    clock : Clock
        The discovery budget (what is left bounds the CPU time).
    base_cpu_s : float
        CPU seconds of the base fit.

    Returns
    -------
    tuple of (float, int)
        The CPU safety net and the iterations per start.
    """
    cpu = min(fit_req.options.max_cpu_time, max(clock.left(), 1.0),
              max(MULTISTART_CPU_FLOOR_S, MULTISTART_CPU_FACTOR * base_cpu_s))
    iters = max(MULTISTART_MIN_ITER, MULTISTART_ITER_FACTOR * int(base.solver.iterations or 0))
    return cpu, min(fit_req.options.max_iter, MULTISTART_MAX_ITER, iters)


def _multistart(fit_req: FitRequest, base: FitResult, clock: Clock, notes: list[str],
                base_cpu_s: float) -> FitResult:
    codes = {w.code for w in base.warnings}
    if base.quality != "suspect" or not codes & LOCAL_MINIMUM_CODES or fit_req.options.multistart > 1:
        return base
    # bounded by starts and iterations; the CPU limit is only the safety net
    cpu, max_iter = multistart_bounds(fit_req, base, clock, base_cpu_s)
    req = fit_req.model_copy(update={"options": fit_req.options.model_copy(update={
        "multistart": MULTISTART_STARTS, "max_cpu_time": cpu, "max_iter": max_iter})})
    why = f"the base fit was suspect ({', '.join(sorted(codes & LOCAL_MINIMUM_CODES))})"
    try:
        best = fit_model(req)
    except (FitError, RuntimeError, ValueError) as exc:
        notes.append(f"{why}; a multistart of {MULTISTART_STARTS} starts failed ({exc}); the search starts "
                     "from the base fit")
        return base
    status = best.solver.return_status
    if status in CPU_STATUSES:
        notes.append(f"{why}; a multistart of {MULTISTART_STARTS} starts was cut off by its CPU limit of "
                     f"{cpu:.3g} s ({MULTISTART_CPU_FACTOR:g}× the base fit's, at most options.max_cpu_time and "
                     f"what was left of discovery.time_budget_s; "
                     f"{status}): it is no answer, and whether a start does better is not known; the search "
                     "starts from the base fit (raise max_cpu_time or time_budget_s for the multistart)")
        return base
    if best.quality == "failed" or best.metrics.cost is None or base.metrics.cost is None:
        notes.append(f"{why}; a multistart of {best.solver.starts} starts did not converge ({status}); the "
                     "search starts from the base fit")
        return base
    if not best.metrics.cost < base.metrics.cost * (1 - 1e-6):
        notes.append(f"{why}; a multistart of {best.solver.starts} starts found no better minimum")
        return base
    notes.append(f"{why}, perhaps at a local minimum: a multistart of {best.solver.starts} starts lowered the "
                 f"cost from {base.metrics.cost:.4g} to {best.metrics.cost:.4g}; the search starts from that fit")
    return best
