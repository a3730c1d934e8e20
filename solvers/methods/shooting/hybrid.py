"""The solver of multiple shooting: Gauss-Newton to get near, the gaps' curvature to finish.

Why and how the curvature is built: `curvature.py`. `make_solver` is the one place a fit's solver is chosen.
"""
from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from greyfit.schemas.fit import FitOptions
from greyfit.solvers.nlp.problem import LeastSquaresProblem
from greyfit.solvers.nlp.protocol import Solver
from greyfit.solvers.nlp.solver import LeastSquaresSolver, NlpOutcome

# Ipopt regularises an indefinite Hessian by adding δI, δ up to this; beyond it the iteration
# fails (restoration) instead of trying ~20 factorisations per iteration: the exact curvature of
# a stiff tanh(v/ε) term took 13 s per iteration that way, Gauss-Newton then takes over.
MAX_HESSIAN_PERTURBATION = 1e6


GN_ITERATIONS = 50          # plain Gauss-Newton iterations before the curvature is added


CURVATURE_ITERATIONS = 50   # then with it: near the optimum it converges in 5-30 (tanks, EMPS)


def make_solver(problem: LeastSquaresProblem, options: FitOptions) -> Solver:
    """The solver `fit_model` uses: the hybrid for multiple shooting, the structured form where the
    problem has one (solvers/methods/shooting/structured.py), else plain Gauss-Newton.

    Parameters
    ----------
    problem : LeastSquaresProblem
        The method's least-squares NLP.
    options : FitOptions
        The request's options (``hessian``, ``max_iter``, ``max_cpu_time``, ...).

    Returns
    -------
    Solver
        `HybridShootingSolver` for multiple shooting with the Gauss-Newton Hessian; otherwise the
        problem's own (structured) solver when it has one, else a `LeastSquaresSolver`.
    """
    shooting = problem.constraint_hessian is not None or problem.graph_builder is not None
    if not shooting or options.hessian != "gauss_newton":
        return problem.solver_factory() if problem.solver_factory is not None else LeastSquaresSolver(problem, options)
    return HybridShootingSolver(problem, options)


def plain_gauss_newton_solver(problem: LeastSquaresProblem, options: FitOptions,
                              max_iter: int | None = None) -> Solver:
    """What "plain Gauss-Newton" means for multiple shooting: JᵀJ without the gaps' curvature, in
    the structured form where the problem has one (the solver every Gauss-Newton fit used before
    the hybrid), else over the CasADi graph; the request's max_iter unless given.

    The two forms are the same NLP but not the same arithmetic: on a problem that does not
    converge their iterates drift apart (cost 2.5 vs 15.7 after 200 iterations on the tanh test),
    so the hybrid's fallback and the comparison in its test both use this one.

    Parameters
    ----------
    problem : LeastSquaresProblem
        The method's least-squares NLP.
    options : FitOptions
        The request's options (``hessian``, ``max_iter``, ``max_cpu_time``, ...).
    max_iter : int, optional
        Iteration limit; None keeps the request's ``max_iter``.

    Returns
    -------
    Solver
        The structured solver when the problem has one, else a `LeastSquaresSolver` without the curvature.
    """
    if problem.solver_factory is not None:
        return problem.solver_factory(max_iter=max_iter)
    extra = {} if max_iter is None else {"max_iter": max_iter}
    return LeastSquaresSolver(problem, options, curvature=False, ipopt=extra)


def make_warm_solver(problem: LeastSquaresProblem, options: FitOptions) -> Solver:
    """For re-optimisations that start next to an optimum (profile points): multiple shooting goes
    straight to the curvature phase, where Gauss-Newton would first circle a misfitting optimum and
    could wander into a degenerate region (an iteration there took 30 s).

    Parameters
    ----------
    problem : LeastSquaresProblem
        The method's least-squares NLP.
    options : FitOptions
        The request's options (``hessian``, ``max_iter``, ``max_cpu_time``, ...).

    Returns
    -------
    Solver
        For multiple shooting with the Gauss-Newton Hessian, a `LeastSquaresSolver` over the graph with
        the gaps' curvature; otherwise `make_solver`'s choice.
    """
    shooting = problem.constraint_hessian is not None or problem.graph_builder is not None
    if not shooting or options.hessian != "gauss_newton":
        return make_solver(problem, options)
    return LeastSquaresSolver(problem.graph(), options, curvature=True,
                              ipopt={"max_hessian_perturbation": MAX_HESSIAN_PERTURBATION})


CPU_LIMIT_STATUS = "Maximum_CpuTime_Exceeded"


class HybridShootingSolver:
    """Gauss-Newton to get near, the gaps' curvature to finish.

    1. Plain Gauss-Newton for up to GN_ITERATIONS: well-posed fits converge there (seed 000's
       seat model in 7) at the old cost, and far from the optimum its positive semidefinite
       Hessian is the more forgiving (with the curvature first, seed 001's closed loop from a
       start at 5x a1 settled in a local minimum that Gauss-Newton passes).
    2. Not converged: from that iterate, Gauss-Newton plus the curvature for up to
       CURVATURE_ITERATIONS (misfitting models: the tanks' optimum, which Gauss-Newton circles
       with growing steps, in 5 more iterations); and the same from the start w0, because step 1
       may have walked into a degenerate region (a linear model on a cascaded-tanks-like record:
       Gauss-Newton took a, b, d -> 0 and the curvature converged there at 3.4x the optimum's
       cost, which the curvature from w0 reaches in 13 iterations).
    3. Neither converges (a nearly non-smooth model, whose exact curvature is huge and indefinite):
       `plain_gauss_newton_solver` from the same start w0 with the full max_iter, i.e. exactly the
       run a plain Gauss-Newton fit makes (its first iterations repeat step 1).

    The result is the best of the runs: converged first, then the lower cost. So by construction
    it is converged, or its cost is at most that of plain Gauss-Newton from w0.

    Every phase is bounded by iterations, so the answer does not depend on machine load.
    `options.max_cpu_time` is a safety net only: each phase runs under it, and when a phase hits
    it or the phases together exceed it, the solve ends with status Maximum_CpuTime_Exceeded
    (not converged), never with an answer that a quiet machine would not give.
    """

    def __init__(self, problem: LeastSquaresProblem, options: FitOptions):
        self.problem, self.options = problem, options
        self.short: Solver = plain_gauss_newton_solver(problem, options,
                                                       max_iter=min(GN_ITERATIONS, options.max_iter))
        self.compiled = self.short.compiled   # read again after each solve: the next may start in C (handover.py)
        self.curved: LeastSquaresSolver | None = None
        self.plain: Solver | None = None
        self.phases: list[str] = []   # what the last solve did, for tests and notes
        self.outcomes: list[NlpOutcome] = []   # each phase's outcome in the last solve

    def _curvature_solver(self) -> LeastSquaresSolver:
        if self.curved is None:
            self.curved = LeastSquaresSolver(
                self.problem.graph(), self.options, curvature=True,
                ipopt={"max_hessian_perturbation": MAX_HESSIAN_PERTURBATION,
                       "max_iter": min(CURVATURE_ITERATIONS, self.options.max_iter)})
        return self.curved

    def _plain_solver(self) -> Solver:
        if self.plain is None:
            self.plain = plain_gauss_newton_solver(self.problem, self.options)
        return self.plain

    def solve(self, w0: np.ndarray, lbw: np.ndarray | None = None, ubw: np.ndarray | None = None) -> NlpOutcome:
        """Run the phases from `w0` and return the best (see the class docstring).

        Parameters
        ----------
        w0 : numpy.ndarray
            Start of the NLP's decision vector (scaled).
        lbw, ubw : numpy.ndarray, optional
            Bounds on the decision vector; None keeps the problem's.

        Returns
        -------
        NlpOutcome
            The best run (converged first, then the lower cost), with the iterations and wall time of all
            phases summed; status ``Maximum_CpuTime_Exceeded`` and not converged when the CPU limit cut it.
        """
        cpu0 = time.process_time()
        runs = [self.short.solve(w0, lbw, ubw)]
        self.compiled = self.short.compiled
        self.phases, self.outcomes = ["gauss_newton"], runs
        if runs[0].success or self.options.max_iter <= GN_ITERATIONS:
            return runs[0]
        w1 = runs[0].w if np.all(np.isfinite(runs[0].w)) else w0
        later = [("curvature", self._curvature_solver, w1), ("curvature_from_start", self._curvature_solver, w0),
                 ("plain_gauss_newton", self._plain_solver, w0)]
        for name, make, start in later:
            if _out_of_time(runs, cpu0, self.options.max_cpu_time):
                break
            if name == "plain_gauss_newton" and any(o.success for o in runs):
                break
            runs.append(make().solve(start, lbw, ubw))
            self.phases.append(name)
        self.outcomes = runs
        best = max(runs, key=lambda o: (o.success, -o.cost if np.isfinite(o.cost) else -np.inf))
        best = replace(best, iterations=sum(o.iterations for o in runs),
                       wall_time_s=sum(o.wall_time_s for o in runs))
        if _out_of_time(runs, cpu0, self.options.max_cpu_time):
            # cut off by the safety net: what it reached is not the answer a quiet run gives
            best = replace(best, status=CPU_LIMIT_STATUS, success=False)
        return best


def _out_of_time(runs: list[NlpOutcome], cpu0: float, limit: float) -> bool:
    """Whether a phase hit the CPU limit or the phases together used it up."""
    return any(o.status == CPU_LIMIT_STATUS for o in runs) or time.process_time() - cpu0 > limit
