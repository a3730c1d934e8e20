"""Multistart: the starts, their solves, and how far they agree (issue #22).

Why: a fit from several starts used to return its best and say only how many starts ran. Where
several distinct parameter vectors explain the data equally well (A→B→C kinetics with only C
measured: k1 and k2 swap; a coarsely sampled step: several ωn), the one returned is an accident of
the starts, and a `good` verdict on it is wrong.

What: every start runs to its own end under iteration limits only, so the set of optima does not
depend on machine load. `options.max_cpu_time` is a safety net: when it runs out before every start
ran, the fit ends not converged with status MULTISTART_CPU_STATUS, the best start so far reported.
After the fit `multistart_agreement` counts the starts that reached the best cost and lists the
distinct converged optima whose cost is statistically indistinguishable from it; more than one is
the `multiple_optima` warning, which makes the result `suspect`.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np

from greyfit.schemas.fit import AlternativeOptimum, FitOptions, FitWarning
from greyfit.solvers.dynamics.integration import integrator_of
from greyfit.solvers.inference.statistics import student_t_quantile
from greyfit.solvers.methods.shooting import OutputErrorModel
from greyfit.solvers.methods.shooting.hybrid import make_solver
from greyfit.solvers.model.parameters import ParameterLayout
from greyfit.solvers.nlp.problem import LeastSquaresProblem
from greyfit.solvers.nlp.solver import LeastSquaresSolver, NlpOutcome, solve_linear_least_squares

MULTISTART_CPU_STATUS = "Multistart_CpuTime_Exceeded"
CPU_STATUSES = {MULTISTART_CPU_STATUS, "Maximum_CpuTime_Exceeded"}
SAME_COST = 1e-6           # relative cost difference of starts that "reached the best cost"
DISTINCT_RELATIVE = 1e-2   # optima differing by more than this in some parameter are distinct
MAX_ALTERNATIVES = 10      # optima listed at most (the best first)
POLISH_MAX_RESIDUALS = 20_000   # beyond, no exact-Hessian polish of an unconverged fit
# nor from an iterate whose constraints are violated by more than this (multiple shooting: a gap of a
# state's whole scale): its trajectory broke apart, it is no flat valley next to an answer. Measured:
# a cubic damping refit (discovery's power-law contender) diverged to gaps of 4e10 in 20 Gauss-Newton
# iterations (1 s), and the exact-Hessian polish from there spent 130 s of CPU in MUMPS' factorisations
# (fill-in reallocated up to 320x, regularisation 1e19) without a step forward
POLISH_MAX_INFEASIBILITY = 1.0


@dataclass
class MultistartRun:
    """The best outcome, every start's outcome in order, and what the solver ran as."""

    best: NlpOutcome
    outcomes: list[NlpOutcome] = field(default_factory=list)
    planned: int = 1
    compiled: bool | None = None
    polished: bool = False   # the best is `polish_with_exact_hessian`'s

    @property
    def used(self) -> int:
        """Number of starts that ran.

        Returns
        -------
        int
            The number of outcomes recorded, at least 1 (a closed-form solve counts as one).
        """
        return max(len(self.outcomes), 1)


@dataclass
class Agreement:
    starts_at_best: int
    optima: list[AlternativeOptimum]
    warnings: list[FitWarning]


def draw_starts(layout: ParameterLayout, n: int, seed: int) -> list[np.ndarray]:
    """The user's guess first, then n-1 draws inside the bounds (log-uniform over decades).

    Parameters
    ----------
    layout : the parameter layout (bounds, initial values, scales).
    n : number of starts, the guess included.
    seed : seed of the random draws (the same seed gives the same starts).

    Returns
    -------
    list of physical parameter vectors.
    """
    starts = [layout.initial.copy()]
    rng = np.random.default_rng(seed)
    for _ in range(n - 1):
        theta = np.empty(layout.size)
        for i in range(layout.size):
            lo, hi, v = layout.lower[i], layout.upper[i], layout.initial[i]
            lo = lo if np.isfinite(lo) else v - 0.5 * layout.scale[i]
            hi = hi if np.isfinite(hi) else v + 0.5 * layout.scale[i]
            if lo > 0 and hi / lo > 10:
                theta[i] = np.exp(rng.uniform(np.log(lo), np.log(hi)))
            else:
                theta[i] = rng.uniform(lo, hi)
        starts.append(theta)
    return starts


def _rank(o: NlpOutcome) -> tuple[bool, float]:
    """Converged first, then the lower cost; a non-finite cost ranks last."""
    return o.success, -o.cost if np.isfinite(o.cost) else -np.inf


def _better(a: NlpOutcome, b: NlpOutcome | None) -> bool:
    return b is None or _rank(a) > _rank(b)


def exact_form(build, oem, problem):
    """() -> `problem` built by `build` (single or multiple shooting) with the exact Hessian: the
    structured form has no CasADi graph to take second derivatives of.

    Parameters
    ----------
    build : callable
        OutputErrorModel -> LeastSquaresProblem (the method's problem builder).
    oem : OutputErrorModel
        The fit's output-error model (its model, data, layout and options are reused).
    problem : LeastSquaresProblem
        The problem being solved; its `penalty` is carried over to the rebuilt one.

    Returns
    -------
    callable
        () -> LeastSquaresProblem built with ``hessian="exact"``; nothing is built until it is called.
    """
    def make():
        exact = OutputErrorModel(oem.cm, oem.data, oem.layout, oem.options.model_copy(update={"hessian": "exact"}))
        rebuilt = build(exact)
        rebuilt.penalty = problem.penalty
        return rebuilt
    return make


def polish_with_exact_hessian(problem, options: FitOptions, run: MultistartRun, exact=None) -> None:
    """When no Gauss-Newton start converged: Ipopt with the exact Hessian from the best iterate.

    Why: on a flat valley Gauss-Newton crawls without meeting the tolerance (a linear two-tank
    model on a cascaded-tanks-like record, whose optimum has a double pole: 2000 iterations and
    still not converged; the exact Hessian from the same start in 11). Bounded by max_iter like
    every other solve; kept only if it converges, and then `run.polished` says so. Not tried
    with an integrator whose step is not symbolic (CVODES: its exact Hessian takes second-order
    sensitivities), beyond POLISH_MAX_RESIDUALS residuals (the exact Hessian of a long graph
    takes long to build), nor from an iterate that diverged (constraint violation above
    POLISH_MAX_INFEASIBILITY).
    `exact`: () -> the problem in a form with a graph (`exact_form`); else `problem.graph()`.

    Parameters
    ----------
    problem : LeastSquaresProblem
        The problem that was solved.
    options : FitOptions
        The request's options (Hessian, integrator, iteration and CPU limits).
    run : MultistartRun
        The multistart's outcomes; changed in place.
    exact : callable, optional
        () -> the problem with a CasADi graph (`exact_form`); None uses `problem.graph()`.

    Returns
    -------
    None
        `run.best` is replaced by the polished outcome (iterations added) and `run.polished` set when it
        converges; when the polish runs out of CPU time, `run.best` keeps its iterate, not converged, with
        that status.
    """
    best = run.best
    if best.success or options.hessian != "gauss_newton" or not integrator_of(options).symbolic \
            or best.status in CPU_STATUSES or not np.all(np.isfinite(best.w)) \
            or not best.infeasibility <= POLISH_MAX_INFEASIBILITY:
        return
    graph = exact() if exact is not None else problem.graph()
    if graph is None or graph.residual.numel() > POLISH_MAX_RESIDUALS:
        return
    out = LeastSquaresSolver(graph, options.model_copy(update={"hessian": "exact"})).solve(best.w)
    if out.status in CPU_STATUSES:   # the safety net: not an answer a quiet machine would give
        run.best = replace(best, status=out.status, success=False)
    elif out.success:
        run.best = replace(out, iterations=out.iterations + best.iterations)
        run.polished = True


def multistart_warnings(run: MultistartRun | None, agreement: "Agreement | None") -> list[FitWarning]:
    """`multiple_optima` (suspect) and `polished_with_exact_hessian` (info) where they apply.

    Parameters
    ----------
    run : MultistartRun or None
        The multistart's outcomes (None: the fit was solved otherwise).
    agreement : Agreement or None
        The result of `multistart_agreement` (None: one start).

    Returns
    -------
    list of FitWarning
        The agreement's warnings, then `polished_with_exact_hessian` when the best was polished.
    """
    out = list(agreement.warnings) if agreement is not None else []
    if run is not None and run.polished:
        out.append(FitWarning(
            code="polished_with_exact_hessian",
            message="Gauss-Newton did not converge (a flat valley, where its Hessian JᵀJ leaves out "
                    "the curvature); Ipopt with the exact Hessian went on from its best iterate and "
                    "converged", detail={"return_status": run.best.status}))
    return out


def solve_from_starts(problem: LeastSquaresProblem, options: FitOptions, starts: list[np.ndarray],
                      linear: bool, cpu0: float | None = None, exact=None) -> MultistartRun:
    """Solve from every start (the closed form instead where `linear` and it applies).

    Parameters
    ----------
    problem : the method's least-squares NLP
    options : the request's options
    starts : physical parameter vectors, the user's guess first (`draw_starts`)
    linear : try `solve_linear_least_squares` first (equation error, affine residual)
    cpu0 : the process time the fit began at; its preparation counts against max_cpu_time too
    exact : for the polish, () -> the problem with a graph (`exact_form`), where it has none

    Returns
    -------
    MultistartRun
        Where no Gauss-Newton start converged, its best is polished with the exact Hessian
        (`polish_with_exact_hessian`). Its `best` is not converged, with status
        MULTISTART_CPU_STATUS, when max_cpu_time would run out before the next start ended
        (judged by the mean CPU time of the starts so far), or when it ended a start's own solve.
    """
    if linear:
        outcome = solve_linear_least_squares(problem, options)
        if outcome is not None:
            return MultistartRun(outcome, [outcome], 1, None)
    solver = make_solver(problem, options)   # multiple shooting: with its gaps' curvature
    outcomes: list[NlpOutcome] = []
    best: NlpOutcome | None = None
    cpu0 = time.process_time() if cpu0 is None else cpu0
    solving = time.process_time()
    for theta0 in starts:
        now = time.process_time()
        if best is not None and now - cpu0 + (now - solving) / len(outcomes) > options.max_cpu_time:
            # the safety net: a cut multistart is not the answer a quiet machine gives
            best = replace(best, status=MULTISTART_CPU_STATUS, success=False)
            return MultistartRun(best, outcomes, len(starts), solver.compiled)
        out = solver.solve(problem.initial_guess(theta0))
        outcomes.append(out)
        if _better(out, best):
            best = out
    if best is None:
        raise ValueError("no start to solve from")   # starts always hold the user's guess
    if len(outcomes) > 1 and any(o.status in CPU_STATUSES for o in outcomes):
        # a start the safety net stopped (the last one: an earlier one's CPU ends the loop above)
        best = replace(best, status=MULTISTART_CPU_STATUS, success=False)
    run = MultistartRun(best, outcomes, len(starts), solver.compiled)
    polish_with_exact_hessian(problem, options, run, exact)
    return run


def multistart_agreement(run: MultistartRun | None, layout: ParameterLayout, ndata: int, nvarys: int,
                         level: float) -> Agreement | None:
    """Starts at the best cost and the distinct optima indistinguishable from it (None: one start).

    Parameters
    ----------
    run : the multistart's outcomes (None: the fit was solved otherwise, e.g. IRLS)
    layout : maps each outcome's scaled θ (its first entries) to named physical values
    ndata, nvarys : residuals and free parameters of the fit (σ² = 2 cost / (ndata − nvarys))
    level : the confidence level; an optimum is indistinguishable when its cost exceeds the best
        by less than ½ t²(ν) σ², the threshold of the profile intervals (`inference/profile.py`)

    Returns
    -------
    Agreement or None
        `optima` holds the best first; only converged starts count as optima. More than one
        optimum gives a `multiple_optima` warning.
    """
    if run is None or len(run.outcomes) < 2 or not np.isfinite(run.best.cost):
        return None
    best = run.best.cost
    at_best = sum(1 for o in run.outcomes if np.isfinite(o.cost)
                  and o.cost - best <= SAME_COST * max(abs(best), 1e-300))
    dof = ndata - nvarys
    if not run.best.success or dof <= 0:
        return Agreement(at_best, [], [])
    t = student_t_quantile(0.5 + level / 2, dof)
    delta = 0.5 * t * t * (2.0 * best / dof)
    groups: list[tuple[np.ndarray, NlpOutcome, int]] = []
    candidates = sorted((o for o in run.outcomes if o.success and np.isfinite(o.cost)
                         and o.cost - best <= delta), key=lambda o: o.cost)
    for o in candidates:
        theta = layout.physical(o.w[:layout.size])
        for k, (ref, first, count) in enumerate(groups):
            if not _distinct(theta, ref, layout.scale):
                groups[k] = (ref, first, count + 1)
                break
        else:
            groups.append((theta, o, 1))
    optima = [AlternativeOptimum(parameters={lab: float(v) for lab, v in zip(layout.labels, theta)},
                                 cost=float(o.cost), starts=count)
              for theta, o, count in groups[:MAX_ALTERNATIVES]]
    return Agreement(at_best, optima, _optima_warning(optima, delta) if len(optima) > 1 else [])


def _distinct(a: np.ndarray, b: np.ndarray, scale: np.ndarray) -> bool:
    floor = 1e-9 * np.abs(scale)
    return bool(np.any(np.abs(a - b) > DISTINCT_RELATIVE * np.maximum(np.maximum(np.abs(a), np.abs(b)), floor)))


def _optima_warning(optima: list[AlternativeOptimum], delta: float) -> list[FitWarning]:
    def show(o: AlternativeOptimum) -> str:
        return ", ".join(f"{k} = {v:.4g}" for k, v in o.parameters.items())
    return [FitWarning(
        code="multiple_optima",
        message=f"{len(optima)} distinct optima explain the data equally well (costs within "
                f"{delta:.3g} of the best, the profile-interval threshold): "
                + "; ".join(f"[{show(o)}]" for o in optima)
                + "; the one returned is an accident of the starts: add data that tells them "
                  "apart, bounds or constraints that exclude all but one",
        detail={"optima": [o.model_dump() for o in optima], "cost_threshold": delta})]
