"""Curvature of multiple shooting's continuity gaps for the Gauss-Newton Hessian (issue #8).

Why: the Gauss-Newton Hessian JᵀJ of the output residual leaves out the constraints' curvature
Σ λᵀ∇²g. In multiple shooting the gaps carry the model and their multipliers grow with the
misfit: for a model that does not fit the data well (the linear two-tank model on sqrt outflows)
the true curvature along some direction was more than twice JᵀJ's, each step overshot the
optimum by a growing factor (x1.14 per iteration from the single-shooting optimum itself) and
Ipopt walked off to a degenerate point (k1, k2 -> 0, an unmeasured level at -1.6e6).

What: each gap depends on one node and θ only, so Σ λᵀ∇²g is a sum of small per-interval blocks
over (node k, θ), computed by one SX Hessian mapped over the intervals and scattered into place;
`ca.hessian` of the whole MX graph gives the same matrix but took 7 s to build for seed 000's
seat model (sparsity detection over every node), this 0.1 s. With it the tanks case converges in
9 iterations to the single-shooting optimum; the seat model's fit takes ~20 % longer.

The exact curvature can be hugely indefinite (a stiff tanh(v/ε) term), and far from the optimum
it can lead into other stationary points than Gauss-Newton's. A positive semidefinite projection
of each block was tried: it destroys the cancellation between intervals in the θθ block and made
the seat model crawl (200 iterations). Hence `HybridShootingSolver`: Gauss-Newton first, the
curvature (with a cap on Ipopt's regularisation) where Gauss-Newton has not converged.
"""
from __future__ import annotations

import time
from dataclasses import replace

import casadi as ca
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


class GapCurvature:
    """Collects the gap blocks in the order `build_multiple_shooting` appends them to g."""

    def __init__(self, oem, map_mode: str = "serial"):
        self.oem, self.map_mode = oem, map_mode
        self.blocks: list[tuple] = []
        self.n_gap = 0
        self._functions: dict[tuple[int, int], tuple[ca.Function, np.ndarray]] = {}

    def add(self, e: int, node_column: int, ks: np.ndarray, length: int, cols: np.ndarray) -> None:
        """Gaps of experiment e for intervals starting at nodes `ks` (each `length` samples,
        starting at sample `cols[j*length]`); node k's scaled states sit at w[node_column + nx k]."""
        self.blocks.append((e, node_column, np.asarray(ks), int(length), np.asarray(cols), self.n_gap))
        self.n_gap += self.oem.cm.nx * len(ks)

    def _interval_hessian(self, e: int, length: int) -> tuple[ca.Function, np.ndarray]:
        """(H(X, θ, λ, U0, U1, T0, DT) dense over z = [X; θ], local indices that take part)."""
        key = (e, length)
        if key not in self._functions:
            oem, cm = self.oem, self.oem.cm
            x_s, th = ca.MX.sym("X", cm.nx), ca.MX.sym("theta", oem.layout.size)
            lam = ca.MX.sym("lam", cm.nx)
            u0, u1 = ca.MX.sym("U0", cm.nu, length), ca.MX.sym("U1", cm.nu, length)
            t0, dt = ca.MX.sym("T0", 1, length), ca.MX.sym("DT", 1, length)
            p = oem.layout.full(e, th)
            xk = ca.DM(oem.xscale) * x_s
            for j in range(length):
                xk = oem.step(xk, u0[:, j], u1[:, j], p, t0[:, j], dt[:, j])
            z = ca.vertcat(x_s, th)
            hess = ca.hessian(ca.dot(lam / ca.DM(oem.xscale), xk), z)[0]
            fn = ca.Function("gap_hessian", [x_s, th, lam, u0, u1, t0, dt], [ca.densify(hess)])
            try:
                fn = fn.expand()   # RK4 and difference equations are SX inside: much faster
            except RuntimeError:
                pass               # CVODES stays an MX call (second-order sensitivities)
            rows, _ = hess.sparsity().get_triplet()
            # dense over the variables that take part (a handful per interval)
            self._functions[key] = (fn, np.unique(np.array(rows, dtype=int)))
        return self._functions[key]

    def bind(self, w: ca.MX, theta: ca.MX, g_par: list[ca.MX]) -> "GapCurvature":
        """The NLP's variables and parameter constraints g_par(θ), which follow the gaps in g."""
        self.w, self.theta, self.g_par = w, theta, g_par
        return self

    def __call__(self, lam_g: ca.MX) -> ca.MX:
        """Σ λᵀ∇²g for g = [gaps; g_par(θ)]."""
        w, theta = self.w, self.theta
        total = self.hessian(w, lam_g)
        if self.g_par:
            nth = theta.numel()
            h_par = ca.hessian(ca.dot(lam_g[self.n_gap:], ca.vertcat(*self.g_par)), theta)[0]
            total = total + ca.diagcat(h_par, ca.MX(w.numel() - nth, w.numel() - nth))
        return total

    def hessian(self, w: ca.MX, lam_g: ca.MX) -> ca.MX:
        """Σ_gaps λᵀ∇²g as an (n_w × n_w) MX; λ is the first `n_gap` entries of lam_g."""
        oem, cm = self.oem, self.oem.cm
        n_w = w.numel()
        nx, nth = cm.nx, oem.layout.size
        theta = w[:nth]
        vals, rows, cols = [], [], []
        hth = ca.MX(nth, nth)
        for e, node_column, ks, length, scols, g0 in self.blocks:
            if ks.size == 0:
                continue
            d = oem.data[e]
            fn, act = self._interval_hessian(e, length)
            if act.size == 0:
                continue   # linear gaps: no curvature
            m = ks.size
            span = w[node_column: node_column + nx * (int(ks.max()) + 1)]
            x_nodes = ca.reshape(span, nx, int(ks.max()) + 1)[:, ks.tolist()]
            lam = ca.reshape(lam_g[g0: g0 + nx * m], nx, m)
            h = fn.map(m, self.map_mode)(x_nodes, ca.repmat(theta, 1, m), lam, d.u[:, scols],
                                         d.u[:, scols + 1], d.t[scols][None, :],
                                         (d.t[scols + 1] - d.t[scols])[None, :])   # nz × (nz m)
            na = act.size
            cols_sel = (np.arange(m)[:, None] * (nx + nth) + act[None, :]).ravel()
            h = h[act.tolist(), cols_sel.tolist()]                              # na × (na m)
            # θθ parts of all intervals add up; node parts are each interval's own
            th_loc = np.flatnonzero(act >= nx)
            if th_loc.size:
                summed = ca.reshape(ca.sum2(ca.reshape(h, na * na, m)), na, na)
                idx = (act[th_loc] - nx).tolist()
                block = ca.MX(nth, nth)
                block[idx, idx] = summed[th_loc.tolist(), th_loc.tolist()]
                hth += block
            a_grid, b_grid = np.meshgrid(np.arange(na), np.arange(na), indexing="ij")
            a_loc, b_loc = a_grid.ravel(order="F"), b_grid.ravel(order="F")   # vec (column-major) order
            node_part = (act[a_loc] < nx) | (act[b_loc] < nx)
            a_keep, b_keep = act[a_loc[node_part]], act[b_loc[node_part]]
            flat = (b_loc * na + a_loc)[node_part]
            flat_all = (np.arange(m)[:, None] * na * na + flat[None, :]).ravel()   # in vec(h) order
            node0 = node_column + nx * ks
            glob = lambda loc, base: np.where(loc < nx, base + loc, loc - nx)   # noqa: E731
            rows.append(glob(a_keep[None, :], node0[:, None]).ravel())
            cols.append(glob(b_keep[None, :], node0[:, None]).ravel())
            vals.append(ca.vec(h)[flat_all.tolist()])
        total = ca.diagcat(hth, ca.MX(n_w - nth, n_w - nth))
        if vals:
            r, c = np.concatenate(rows), np.concatenate(cols)
            # each (node, local entry) occurs once: mapping[nonzero] = its triplet
            sp, mapping = ca.Sparsity.triplet(n_w, n_w, r.tolist(), c.tolist(), False)
            total = total + ca.MX(sp, ca.vertcat(*vals)[list(mapping)])
        return total


def make_solver(problem: LeastSquaresProblem, options: FitOptions) -> Solver:
    """The solver `fit_model` uses: the hybrid for multiple shooting, the structured form where the
    problem has one (solvers/methods/shooting_structured.py), else plain Gauss-Newton."""
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
    """
    if problem.solver_factory is not None:
        return problem.solver_factory(max_iter=max_iter)
    extra = {} if max_iter is None else {"max_iter": max_iter}
    return LeastSquaresSolver(problem, options, curvature=False, ipopt=extra)


def make_warm_solver(problem: LeastSquaresProblem, options: FitOptions) -> Solver:
    """For re-optimisations that start next to an optimum (profile points): multiple shooting goes
    straight to the curvature phase, where Gauss-Newton would first circle a misfitting optimum and
    could wander into a degenerate region (an iteration there took 30 s)."""
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
        self.compiled = self.short.compiled
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
        cpu0 = time.process_time()
        runs = [self.short.solve(w0, lbw, ubw)]
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
