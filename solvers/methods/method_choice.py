"""`method: auto`: single shooting where the model can be simulated from the start guess, else
multiple shooting; and, once, multiple shooting after a single-shooting answer that is not to be trusted.

Why: multiple shooting makes the state at every node a decision variable, so its KKT system is
about (states + 1) × the samples (on a 2-state record 2N), and the sparse factorisation is most of
its time; single shooting solves the same least-squares problem over the parameters and free
initial states only, at 0.26–0.46× the CPU where one simulation from the start is usable. The
nodes earn their cost where it is not: a simulation at the guess that fails, runs away from the
data's scale, or grows like an unstable linearisation (its sensitivities then grow alike, and the
single-shooting NLP is ill-conditioned or has many local minima). Both methods have the same
optimum; which one ran, and why, is `solver.method_choice`.
"""
from __future__ import annotations

import math

import casadi as ca
import numpy as np

from greyfit.schemas.fit import FitMethod, FitResult, MethodChoice
from greyfit.solvers.dynamics.columns import Columns
from greyfit.solvers.methods.node_initialisation import DIVERGED
from greyfit.solvers.methods.shooting.model import OutputErrorModel
from greyfit.solvers.model.compiler import CompiledModel

OUTPUT_BLOWUP = 100.0           # simulated output beyond this × the measured range: runs away
GROWTH_LIMIT = math.log(1e6)    # ∫ max Re λ(∂f/∂x) dt above this: unstable over the record
GROWTH_POINTS = 50              # points of each simulation the linearisation is evaluated at
# warnings on a single-shooting answer that multiple shooting, from nodes at the data, can repair
FALLBACK_CODES = ("simulation_failed", "non_finite_cost", "not_converged", "fit_below_noise_level",
                  "extreme_state")
COST_MARGIN = 1e-6              # relative: multiple shooting's answer replaces single shooting's
                                # only when its cost is lower by more than this
# the CPU limit's statuses (Ipopt's; a multistart's, solvers/methods/multistart.py): a safety net,
# whose answer a quiet machine would not give
CPU_STATUSES = ("Maximum_CpuTime_Exceeded", "Multistart_CpuTime_Exceeded")


def choose_shooting(oem: OutputErrorModel) -> MethodChoice:
    """Single or multiple shooting for `auto`, from one simulation at the start guess.

    Parameters
    ----------
    oem : OutputErrorModel
        The output-error model, its layout's initial values the start guess; the simulation is
        kept in its cache (the pre-fit checks and the nodes simulate the same point), a failure of
        it is not kept in `oem.simulation_failures` (the pre-fit checks report it).

    Returns
    -------
    MethodChoice
        ``requested`` auto, ``ran`` single_shooting or multiple_shooting, and the reason.
    """
    if "shooting_interval" in oem.options.model_fields_set:
        return _choice(FitMethod.multiple_shooting, "options.shooting_interval is set: it spaces multiple "
                                                    "shooting's nodes, so the nodes were asked for")
    failures = len(oem.simulation_failures)
    sims = oem.simulate(oem.layout.initial, [oem.x0_guess(e) for e in range(len(oem.data))])
    failed = oem.simulation_failures[failures:]
    del oem.simulation_failures[failures:]
    why = _unusable(oem, sims, failed)
    if why:
        return _choice(FitMethod.multiple_shooting, f"{why}: multiple shooting starts its nodes at the data")
    growth, where = _growth(oem, [xs for xs, _ in sims])
    if growth > GROWTH_LIMIT:
        return _choice(FitMethod.multiple_shooting,
                       f"the model linearised along the simulation at the start guess grows by "
                       f"e^{growth:.3g} over experiment '{where}' (unstable; single shooting's sensitivities "
                       f"would grow alike): multiple shooting")
    return _choice(FitMethod.single_shooting,
                   f"the simulation at the start guess is finite, stays within {OUTPUT_BLOWUP:g}× the "
                   f"measured range and does not grow (linearised growth e^{growth:.2g} at most, limit "
                   f"e^{GROWTH_LIMIT:.3g}): single shooting, no nodes needed")


def _choice(ran: FitMethod, reason: str) -> MethodChoice:
    return MethodChoice(requested=FitMethod.auto, ran=ran, reason=reason)


def _unusable(oem: OutputErrorModel, sims: list[tuple[np.ndarray, np.ndarray]], failed: list[str]) -> str:
    """Why the simulation at the guess cannot start single shooting, or ""."""
    cm = oem.cm
    if failed:
        return failed[0].replace("the simulation", "the simulation at the start guess", 1)
    for d, (xs, _) in zip(oem.data, sims):
        bad = ~np.isfinite(xs) | (np.abs(xs) > DIVERGED)
        if bad.any():
            i = int(np.argmax(bad.any(axis=1)))   # the first state in order, as the message names one
            return (f"state '{cm.states[i]}' of the simulation at the start guess runs away (beyond "
                    f"{DIVERGED:.0e} or not finite) at t = {d.t[int(np.argmax(bad[i]))]:.4g} in experiment "
                    f"'{d.name}'")
    centre, scale = _measured_centres(oem)
    excess = [np.abs(ys - centre[:, None]) / scale[:, None] for _, ys in sims]
    beyond = [~np.isfinite(x) | (x > OUTPUT_BLOWUP) for x in excess]
    for j, out in enumerate(cm.outputs):
        if not np.isfinite(centre[j]):   # never measured
            continue
        for d, x, b in zip(oem.data, excess, beyond):
            if b[j].any():
                k = int(np.argmax(b[j]))
                return (f"output '{out}' of the simulation at the start guess reaches "
                        f"{float(x[j, k]):.3g}× the measured range at t = {d.t[k]:.4g} in experiment "
                        f"'{d.name}'")
    return ""


def _measured_centres(oem: OutputErrorModel) -> tuple[np.ndarray, np.ndarray]:
    """Per output, the median of its measured samples and their range (NaN where never measured)."""
    ny = oem.cm.ny
    ys = [d.y for d in oem.data]
    if all(np.isfinite(y).all() for y in ys):   # the usual record: one pass over all outputs
        measured = ys[0] if len(ys) == 1 else np.concatenate(ys, axis=1)
        if measured.shape[1]:
            ptp, top = np.ptp(measured, axis=1), np.max(np.abs(measured), axis=1)
            return np.median(measured, axis=1), np.maximum(np.maximum(ptp, 1e-6 * top), 1e-300)
    centre, scale = np.full(ny, np.nan), np.ones(ny)
    for j in range(ny):
        measured = np.concatenate([y[j][np.isfinite(y[j])] for y in ys])
        if measured.size:
            centre[j] = float(np.median(measured))
            scale[j] = max(float(np.ptp(measured)), 1e-6 * float(np.max(np.abs(measured))), 1e-300)
    return centre, scale


def _growth(oem: OutputErrorModel, states: list[np.ndarray]) -> tuple[float, str]:
    """(largest ∫ max(0, max Re λ(∂f/∂x)) dt over the records, the experiment it is in).

    An upper estimate of how much a perturbation of the start can grow along the simulation (a
    stable model gives 0); a difference equation's Jacobian has multipliers, not rates, and is
    left out (0)."""
    cm = oem.cm
    if cm.model.discrete is not None or cm.nx == 0:
        return 0.0, ""
    jac = state_jacobian_columns(cm)
    worst, where = 0.0, ""
    for e, d in enumerate(oem.data):
        ks = np.unique(np.linspace(0, d.n - 1, min(d.n, GROWTH_POINTS)).astype(int))
        if ks.size < 2:
            continue
        p = np.asarray(oem.layout.full(e, oem.layout.initial / oem.layout.scale), dtype=float).ravel()
        a, = jac(states[e][:, ks], d.u[:, ks], p, d.t[None, ks], n=ks.size)
        blocks = a.reshape(cm.nx, ks.size, cm.nx).transpose(1, 0, 2)
        rates = np.zeros(ks.size)
        ok = np.all(np.isfinite(blocks), axis=(1, 2))
        if ok.any():
            rates[ok] = np.maximum(np.max(eigenvalues(blocks[ok]).real, axis=1), 0.0)
        t = d.t[ks]
        growth = float(np.sum(0.5 * (rates[1:] + rates[:-1]) * np.diff(t)))
        if growth > worst:
            worst, where = growth, d.name
    return worst, where


def state_jacobian_columns(cm) -> Columns:
    """∂f/∂x on numpy columns (x, u, p, t per sample), one per model structure: the method choice's
    growth along the start's simulation and the step-size check's fastest rate read the same one
    (each built, and compiled, its own copy).

    Parameters
    ----------
    cm : CompiledModel
        The compiled model (a stand-in model's is not compiled).

    Returns
    -------
    Columns
        The (nx × nx) Jacobian per sample, column-major.
    """
    return cm.derive(("dfdx",), lambda: Columns(_state_jacobian(cm), 4 * GROWTH_POINTS,
                                                isinstance(cm, CompiledModel)))


def eigenvalues(blocks: np.ndarray) -> np.ndarray:
    """The eigenvalues of each square block, computed once per distinct block: a model linear in its
    states has one ∂f/∂x all along its trajectory (the seat model's 50 growth points were 50
    identical 8 × 8 eigenvalue problems, 0.5 ms of every `auto` fit).

    Parameters
    ----------
    blocks : numpy.ndarray
        (k, n, n) finite matrices.

    Returns
    -------
    numpy.ndarray
        (k, n) complex, as `numpy.linalg.eigvals` gives them block by block.
    """
    k = blocks.shape[0]
    if k > 1 and np.array_equal(blocks, np.broadcast_to(blocks[0], blocks.shape)):
        return np.broadcast_to(np.linalg.eigvals(blocks[:1]), (k, blocks.shape[1]))
    return np.linalg.eigvals(blocks)


def _state_jacobian(cm) -> ca.Function:
    x, u, p, t = ca.SX.sym("x", cm.nx), ca.SX.sym("u", cm.nu), ca.SX.sym("p", cm.np), ca.SX.sym("t")
    return ca.Function("dfdx", [x, u, p, t], [ca.jacobian(cm.rhs(x, u, p, t), x)])


def fallback_reason(result: FitResult) -> str:
    """Why single shooting's answer should be tried again by multiple shooting, or "".

    Parameters
    ----------
    result : FitResult
        The result of the single-shooting fit `auto` chose.

    Returns
    -------
    str
        "" when the answer converged without a warning that multiple shooting could repair; else
        what is wrong with it (the failure, or the first warning code in `FALLBACK_CODES`).
    """
    codes = [w.code for w in result.warnings if w.code in FALLBACK_CODES]
    if result.quality == "failed":
        return f"single shooting failed ({result.solver.return_status}{', ' + codes[0] if codes else ''})"
    if codes:
        return f"single shooting's answer has warning {codes[0]}"
    return ""


def keep_better(single: FitResult, multiple: FitResult, why: str) -> FitResult:
    """The better of the single- and multiple-shooting results, its `solver.method_choice` saying so.

    Parameters
    ----------
    single : FitResult
        The single-shooting result `fallback_reason` doubted.
    multiple : FitResult
        The multiple-shooting result of the same request.
    why : str
        `fallback_reason` of `single`.

    Returns
    -------
    FitResult
        `multiple` when `single` failed and `multiple` did not, or when its cost (both are the cost
        of one simulation from the initial state) is lower by more than `COST_MARGIN`; else `single`.
        A `multiple` cut off by the CPU limit is never kept (its answer depends on machine load),
        and the reason says that the CPU limit ended it.
    """
    s_cost, m_cost = _cost(single), _cost(multiple)
    status = multiple.solver.return_status
    if status in CPU_STATUSES:
        single.solver.method_choice = MethodChoice(
            requested=FitMethod.auto, ran=single.solver.method, fallback=True,
            reason=f"{why}; multiple shooting ran after it with the CPU time left (options.max_cpu_time) and "
                   f"was cut off by that limit ({status}): single shooting's answer is kept")
        return single
    if single.quality == "failed" and multiple.quality != "failed":
        better = True
    elif multiple.quality == "failed" and single.quality != "failed":
        better = False
    else:
        better = m_cost < s_cost * (1.0 - COST_MARGIN)
    kept = multiple if better else single
    verdict = (f"multiple shooting's answer is kept (cost {m_cost:.6g}, single shooting's {s_cost:.6g})" if better
               else f"single shooting's answer is kept: multiple shooting did no better (cost {m_cost:.6g}, "
                    f"single shooting's {s_cost:.6g})")
    kept.solver.method_choice = MethodChoice(requested=FitMethod.auto, ran=kept.solver.method,
                                             reason=f"{why}; multiple shooting ran after it: {verdict}",
                                             fallback=True)
    return kept


def _cost(result: FitResult) -> float:
    cost = result.metrics.cost
    return math.inf if cost is None or not math.isfinite(cost) else float(cost)
