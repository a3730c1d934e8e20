"""Multiple shooting with a node at every sample, derivatives assembled from per-sample blocks.

CasADi's automatic Jacobian of the mapped continuity constraints spends most of a fit in the MX
virtual machine (≈150 ms per evaluation for 1000 samples of an 8-state model). Here every sample
contributes a small dense block — ∂gap/∂x_k, ∂gap/∂θ, ∂r/∂x_k, ∂r/∂θ — computed by one mapped call
of a (compiled, cached) stage Function; the sparse constraint Jacobian, the gradient JᵀR and the
Gauss-Newton Hessian JᵀJ are assembled from those blocks. Cost and memory grow linearly in the
record.

Data (inputs, times, measurements, weights, state scales) and the parameter layout enter the NLP
as parameters, so one Ipopt instance serves every fit of the same model structure and record
lengths: a worker builds it once and reuses it (`_SOLVERS`).
"""
from __future__ import annotations

import os
from collections import OrderedDict
from dataclasses import dataclass

import casadi as ca
import numpy as np

from solvers.compiled import compiled
from solvers.problem import LeastSquaresProblem

EXPECTED_ITERATIONS = 20
SOLVER_CACHE_SIZE = 16
_SOLVERS: "OrderedDict[tuple, tuple]" = OrderedDict()


def supports(oem, single: bool = False) -> bool:
    """Structured path: single shooting, or multiple shooting with a node at every sample; the
    Gauss-Newton Hessian; an SX step (RK4 or discrete).

    `GREYFIT_STRUCTURED_SHOOTING=0` forces the generic graph (for benchmarks and diagnosis).
    """
    opts = oem.options
    return (os.environ.get("GREYFIT_STRUCTURED_SHOOTING", "1") != "0"
            and (single or opts.shooting_interval == 1) and opts.hessian == "gauss_newton"
            and (opts.integrator == "rk4" or oem.cm.model.discrete is not None)
            and all(d.n >= 2 for d in oem.data))


def _stage_functions(oem, samples: int, single: bool) -> tuple[list[ca.Function], bool]:
    """The per-sample Functions of one formulation, compiled C where it pays (`solvers.compiled`).

    Multiple shooting: gap(x_k, x_k+1, u0, u1, t0, dt, θ, M, off, xs) and out(x_k, u, t, θ, M, off,
    xs, y, wt), each with its Jacobians in x_k and θ. Single shooting adds sens(z_k, …) -> z_k+1,
    z = [x; vec(S)], S = ∂x/∂[θ, x0], and jrow(∂r/∂x, ∂r/∂θ, vec(S)) -> (∂r/∂[θ, x0])ᵀ.
    """
    o = oem.options
    fns = oem.cm.derive(("stages", o.integrator, o.substeps, o.input_interpolation, oem.layout.size),
                        lambda: _build_stages(oem))
    fns = [fns[1], fns[2], fns[3]] if single else [fns[0], fns[1]]
    out = [compiled(fn, samples * EXPECTED_ITERATIONS) for fn in fns]
    return [fn for fn, _ in out], all(c for _, c in out)


def _build_stages(oem) -> tuple[ca.Function, ...]:
    cm, nth = oem.cm, oem.layout.size
    sx = ca.SX.sym
    xk, xk1, xs = sx("xk", cm.nx), sx("xk1", cm.nx), sx("xs", cm.nx)
    u0, u1, t0, dt = sx("u0", cm.nu), sx("u1", cm.nu), sx("t0"), sx("dt")
    theta, mat, off = sx("theta", nth), sx("M", cm.np, nth), sx("off", cm.np)
    y, wt = sx("y", cm.ny), sx("wt", cm.ny)
    p = off + ca.mtimes(mat, theta)
    xn = oem.step(xs * xk, u0, u1, p, t0, dt) / xs
    gap = xn - xk1
    gap_fn = ca.Function("greyfit_gap", [xk, xk1, u0, u1, t0, dt, theta, mat, off, xs],
                         [gap, ca.jacobian(gap, xk), ca.jacobian(gap, theta)])
    r = wt * (cm.output(xs * xk, u0, p, t0) - y)
    rx, rt = ca.jacobian(r, xk), ca.jacobian(r, theta)
    out_fn = ca.Function("greyfit_out", [xk, u0, t0, theta, mat, off, xs, y, wt], [r, rx, rt])
    nv = nth + cm.nx
    sens = sx("S", cm.nx, nv)
    s_next = ca.mtimes(ca.jacobian(xn, xk), sens) + ca.horzcat(ca.jacobian(xn, theta), ca.SX(cm.nx, cm.nx))
    z = ca.vertcat(xk, ca.vec(sens))
    sens_fn = ca.Function("greyfit_sens", [z, u0, u1, t0, dt, theta, mat, off, xs],
                          [ca.vertcat(xn, ca.vec(s_next))])
    rx_in, rt_in, s_in = sx("rx", cm.ny, cm.nx), sx("rt", cm.ny, nth), sx("s", cm.nx * nv)
    jrow = ca.mtimes(rx_in, ca.reshape(s_in, cm.nx, nv)) + ca.horzcat(rt_in, ca.SX(cm.ny, cm.nx))
    jrow_fn = ca.Function("greyfit_jrow", [rx_in, rt_in, s_in], [jrow.T])
    return gap_fn, out_fn, sens_fn, jrow_fn


class _Blocks:
    """Named blocks of one parameter vector (the data)."""

    def __init__(self):
        self.shapes: list[tuple[str, tuple[int, int]]] = []
        self.size = 0

    def add(self, name: str, rows: int, cols: int) -> int:
        self.shapes.append((name, (rows, cols)))
        self.size += rows * cols
        return self.size - rows * cols

    def views(self, vec: ca.MX) -> dict[str, ca.MX]:
        out, k = {}, 0
        for name, (r, c) in self.shapes:
            out[name] = ca.reshape(vec[k:k + r * c], r, c)
            k += r * c
        return out


def _stacked(count: int, nr: int, nc: int, row0: int, col0: int, col_step: int):
    """(rows, cols) of the entries of `count` blocks nr × nc stored side by side, in vec order.

    Block k covers rows row0 + k·nr … and columns col0 + k·col_step …: col_step = nx for the
    node columns of sample k, 0 for the θ columns every block shares.
    """
    kk, jj, ii = np.meshgrid(np.arange(count), np.arange(nc), np.arange(nr), indexing="ij")
    return (row0 + kk * nr + ii).ravel(), (col0 + kk * col_step + jj).ravel()


def _sparse(nrow: int, ncol: int, rows: np.ndarray, cols: np.ndarray, values: ca.MX) -> ca.MX:
    """MX sparse matrix from triplets (no duplicates); `values` in triplet order."""
    order = np.lexsort((rows, cols))   # CasADi stores column-major
    sp = ca.Sparsity.triplet(nrow, ncol, rows[order].tolist(), cols[order].tolist())
    return ca.MX(sp, values[order.tolist()])


@dataclass
class _Nlp:
    solver: ca.Function


def _data_blocks(oem) -> tuple[ca.MX, dict[str, ca.MX]]:
    """The data parameter vector and its named views (layout of `_data_vector`)."""
    cm, nth = oem.cm, oem.layout.size
    pb = _Blocks()
    for e, d in enumerate(oem.data):
        pb.add(f"U{e}", cm.nu, d.n)
        pb.add(f"T{e}", 1, d.n)
        pb.add(f"Y{e}", cm.ny, d.n)
        pb.add(f"W{e}", cm.ny, d.n)
        pb.add(f"M{e}", cm.np, nth)
        pb.add(f"X0{e}", cm.nx, 1)
    pb.add("off", cm.np, 1)
    pb.add("xs", cm.nx, 1)
    pvec = ca.MX.sym("data", pb.size)
    return pvec, pb.views(pvec)


def _multiple_shooting_terms(oem, gap_fn, out_fn, theta, pv):
    """(w, r, ∂r/∂w, gaps, ∂gaps/∂w): nodes at every sample, blocks placed in sparse matrices."""
    nx, ny, nth = oem.cm.nx, oem.cm.ny, oem.layout.size
    nodes = [ca.MX.sym(f"X{e}", nx, d.n) for e, d in enumerate(oem.data)]
    w = ca.vertcat(theta, *[ca.vec(X) for X in nodes])
    off, xs = pv["off"], pv["xs"]
    gaps, r_parts = [], []
    g_rows, g_cols, g_vals = [], [], []
    r_rows, r_cols, r_vals = [], [], []
    row_g = row_r = 0
    col = nth
    for e, d in enumerate(oem.data):
        n, m = d.n, d.n - 1
        X, U, T, Y, W, M = nodes[e], pv[f"U{e}"], pv[f"T{e}"], pv[f"Y{e}"], pv[f"W{e}"], pv[f"M{e}"]
        G, GX, GT = gap_fn.map(m, "serial")(X[:, :-1], X[:, 1:], U[:, :-1], U[:, 1:], T[:, :-1],
                                            T[:, 1:] - T[:, :-1], theta, M, off, xs)
        R, RX, RT = out_fn.map(n, "serial")(X, U, T, theta, M, off, xs, Y, W)
        gaps.append(ca.vec(G))
        r_parts.append(ca.vec(R))
        # ∂gap_k/∂x_k, ∂gap_k/∂x_k+1 = −I, ∂gap_k/∂θ; ∂r_k/∂x_k, ∂r_k/∂θ
        for rows, cols in (_stacked(m, nx, nx, row_g, col, nx), _stacked(m, nx, nth, row_g, 0, 0)):
            g_rows.append(rows)
            g_cols.append(cols)
        g_vals += [ca.vec(GX), ca.vec(GT)]
        kk, ii = np.meshgrid(np.arange(m), np.arange(nx), indexing="ij")
        g_rows.append((row_g + kk * nx + ii).ravel())
        g_cols.append((col + (kk + 1) * nx + ii).ravel())
        g_vals.append(ca.MX(ca.DM(-np.ones(m * nx))))
        for rows, cols in (_stacked(n, ny, nx, row_r, col, nx), _stacked(n, ny, nth, row_r, 0, 0)):
            r_rows.append(rows)
            r_cols.append(cols)
        r_vals += [ca.vec(RX), ca.vec(RT)]
        row_g += m * nx
        row_r += n * ny
        col += n * nx
    nw = w.numel()
    jac_gap = _sparse(row_g, nw, np.concatenate(g_rows), np.concatenate(g_cols), ca.vertcat(*g_vals))
    jac_r = _sparse(row_r, nw, np.concatenate(r_rows), np.concatenate(r_cols), ca.vertcat(*r_vals))
    return w, ca.vertcat(*r_parts), jac_r, ca.vertcat(*gaps), jac_gap


def _single_shooting_terms(oem, sens_fn, jrow_fn, out_fn, theta, pv):
    """(w, r, ∂r/∂w, no gaps): one simulation per experiment carrying its sensitivities S_k =
    ∂x_k/∂[θ, x0] (the nodes of multiple shooting condensed away), J_k = ∂r_k/∂x S_k + ∂r_k/∂θ."""
    nx, nth = oem.cm.nx, oem.layout.size
    free = [ca.MX.sym(f"x0_{e}", len(f)) for e, f in enumerate(oem.free_x0)]
    w = ca.vertcat(theta, *free)
    nw = w.numel()
    off, xs = pv["off"], pv["xs"]
    seed = np.vstack([np.zeros((nth, nx)), np.eye(nx)]).T.ravel(order="F")   # S_0 = [0 | I]
    r_parts, jac_parts, col = [], [], nth
    for e, d in enumerate(oem.data):
        U, T, Y, W, M = pv[f"U{e}"], pv[f"T{e}"], pv[f"Y{e}"], pv[f"W{e}"], pv[f"M{e}"]
        place = np.zeros((nx, len(oem.free_x0[e])))
        place[oem.free_x0[e], np.arange(len(oem.free_x0[e]))] = 1.0
        x0 = pv[f"X0{e}"] + ca.mtimes(ca.DM(place), free[e])   # the data block is 0 where x0 is free
        z0 = ca.vertcat(x0, ca.DM(seed))
        Z = sens_fn.mapaccum("sim", d.n - 1)(z0, U[:, :-1], U[:, 1:], T[:, :-1], T[:, 1:] - T[:, :-1],
                                             theta, M, off, xs)
        Z = ca.horzcat(z0, Z)
        R, RX, RT = out_fn.map(d.n, "serial")(Z[:nx, :], U, T, theta, M, off, xs, Y, W)
        JT = jrow_fn.map(d.n, "serial")(RX, RT, Z[nx:, :])           # (nθ + nx) × (ny·n)
        jac = JT.T
        cols = [jac[:, :nth]]
        if free[e].numel():
            cols += [ca.MX(jac.size1(), col - nth), jac[:, [nth + i for i in oem.free_x0[e]]]]
            col += free[e].numel()
        cols.append(ca.MX(jac.size1(), nw - col if free[e].numel() else nw - nth))
        jac_parts.append(ca.horzcat(*cols))
        r_parts.append(ca.vec(R))
    return w, ca.vertcat(*r_parts), ca.vertcat(*jac_parts), ca.MX(0, 1), ca.MX(0, nw)


def _build_nlp(oem, terms, theta, pvec, pv, penalty, max_iter: int, max_cpu_time: float) -> _Nlp:
    """The Ipopt instance over (w, r, ∂r/∂w, gaps, ∂gaps/∂w) plus the user's parameter constraints."""
    cm, layout, nth = oem.cm, oem.layout, oem.layout.size
    w, r, jac_r, gaps, jac_gap = terms
    nw = w.numel()
    g_par = []
    if cm.constraint is not None:
        for e in range(_constraint_copies(oem)):
            g_par.append(cm.constraint(pv["off"] + ca.mtimes(pv[f"M{e}"], theta)))
    g_par = ca.vertcat(*g_par) if g_par else ca.MX(0, 1)
    jac_par = ca.horzcat(ca.jacobian(g_par, theta), ca.MX(g_par.numel(), nw - nth))
    g = ca.vertcat(gaps, g_par)
    jac_g = ca.vertcat(jac_gap, jac_par)
    if penalty is not None:
        pen = penalty(theta)
        jac_pen = ca.horzcat(ca.jacobian(pen, theta), ca.MX(pen.numel(), nw - nth))
        r_all, jac_all = ca.vertcat(r, pen), ca.vertcat(jac_r, jac_pen)
    else:
        r_all, jac_all = r, jac_r
    f = 0.5 * ca.sumsqr(r_all)
    sigma, lam_g = ca.MX.sym("sigma"), ca.MX.sym("lam_g", g.numel())
    names_xp = ["x", "p"]
    grad_f = ca.Function("nlp_grad_f", [w, pvec], [f, ca.mtimes(jac_all.T, r_all)], names_xp, ["f", "grad_f_x"])
    jac_g_fn = ca.Function("nlp_jac_g", [w, pvec], [g, jac_g], names_xp, ["g", "jac_g_x"])
    hess = ca.Function("nlp_hess_l", [w, pvec, sigma, lam_g],
                       [sigma * ca.triu(ca.mtimes(jac_all.T, jac_all))],
                       ["x", "p", "lam_f", "lam_g"], ["hess_gamma_x_x"])
    opts = oem.options
    solver = ca.nlpsol("greyfit_structured", "ipopt", {"x": w, "p": pvec, "f": f, "g": g}, {
        "grad_f": grad_f, "jac_g": jac_g_fn, "hess_lag": hess,
        "ipopt.max_iter": max_iter, "ipopt.max_cpu_time": max_cpu_time, "ipopt.tol": opts.tol,
        # QAMD ordering copes with the dense θ columns: the automatic choice spent 8 s of 10 in
        # MUMPS' analysis at 40 000 samples (2 states), QAMD 0.3 s
        "ipopt.mumps_pivot_order": 6,
        "ipopt.print_level": 0, "ipopt.sb": "yes", "print_time": False,
        "calc_lam_p": False, "calc_multipliers": False})
    return _Nlp(solver)


def _data_vector(oem) -> np.ndarray:
    parts = []
    for e, d in enumerate(oem.data):
        mask = d.mask
        x0 = np.zeros(oem.cm.nx)
        for i, v in d.x0_known.items():
            x0[i] = v / oem.xscale[i]
        parts += [d.u.ravel(order="F"), d.t, np.where(mask, d.y, 0.0).ravel(order="F"),
                  (mask * oem.weights[:, None]).ravel(order="F"), oem.layout.matrix[e].ravel(order="F"), x0]
    parts += [oem.layout.offset, oem.xscale]
    return np.concatenate([np.asarray(p, dtype=float).ravel() for p in parts])


class StructuredSolver:
    """`LeastSquaresSolver`'s interface over a cached structured NLP."""

    def __init__(self, nlp: _Nlp, data: np.ndarray, problem: LeastSquaresProblem, compiled_c: bool):
        self.nlp, self.data, self.problem, self.compiled = nlp, data, problem, compiled_c

    def solve(self, w0: np.ndarray, lbw: np.ndarray | None = None, ubw: np.ndarray | None = None):
        from solvers.nlp import run_ipopt
        return run_ipopt(self.nlp.solver, w0, self.problem, p=self.data, lbw=lbw, ubw=ubw)


def _constraint_copies(oem) -> int:
    if oem.cm.constraint is None:
        return 0
    return 1 if all(ex is None for ex in oem.layout.experiment) else len(oem.data)


def constraint_count(oem) -> int:
    return _constraint_copies(oem) * (oem.cm.constraint_equality.size if oem.cm.constraint is not None else 0)


def constraint_lower(oem) -> np.ndarray:
    return np.zeros(constraint_count(oem))


def constraint_upper(oem) -> np.ndarray:
    if oem.cm.constraint is None:
        return np.zeros(0)
    return np.tile(np.where(oem.cm.constraint_equality, 0.0, np.inf), _constraint_copies(oem))


def attach_solver(oem, problem: LeastSquaresProblem, single: bool = False) -> LeastSquaresProblem:
    """Give `problem` (bounds, guesses and readers of single or multiple shooting) the structured
    solver, made when first asked for (after a time-varying penalty may have been attached)."""
    samples = sum(d.n for d in oem.data)
    structure = (single, tuple(d.n for d in oem.data), tuple(map(tuple, oem.free_x0)))
    o = oem.options

    def make_solver(max_iter: int | None = None, max_cpu_time: float | None = None):
        """`max_iter`, `max_cpu_time`: instead of the request's (a phase of a hybrid solve)."""
        iters = o.max_iter if max_iter is None else max_iter
        cpu = o.max_cpu_time if max_cpu_time is None else max_cpu_time
        fns, is_c = _stage_functions(oem, samples, single)
        penalty = problem.penalty
        # the stage Functions (and the constraint) identify the model structure, the rest shapes
        # the NLP; the entry holds those objects, so an id is never reused while it is cached
        owners = (*fns, oem.cm.constraint)
        nlp_key = (*map(id, owners), structure, iters, cpu, o.tol)
        entry = _SOLVERS.get(nlp_key) if penalty is None else None
        if entry is not None and all(a is b for a, b in zip(entry[0], owners)):
            _SOLVERS.move_to_end(nlp_key)
            nlp = entry[1]
        else:
            pvec, pv = _data_blocks(oem)
            theta = ca.MX.sym("theta", oem.layout.size)
            if single:
                out_fn, sens_fn, jrow_fn = fns
                terms = _single_shooting_terms(oem, sens_fn, jrow_fn, out_fn, theta, pv)
            else:
                gap_fn, out_fn = fns
                terms = _multiple_shooting_terms(oem, gap_fn, out_fn, theta, pv)
            nlp = _build_nlp(oem, terms, theta, pvec, pv, penalty, iters, cpu)
            if penalty is None:
                _SOLVERS[nlp_key] = (owners, nlp)
                while len(_SOLVERS) > SOLVER_CACHE_SIZE:
                    _SOLVERS.popitem(last=False)
        return StructuredSolver(nlp, _data_vector(oem), problem, is_c)

    problem.solver_factory = make_solver
    return problem


_JACOBIANS: "OrderedDict[tuple, tuple]" = OrderedDict()


def condensed_jacobian(oem, theta_s: np.ndarray, x0s: list[dict[str, float]]):
    """(J, r, output of each row) of the single-shooting residual w.r.t. [θ, free x0] (scaled), at
    the measured samples: `shooting.sensitivity_jacobian` by one compiled pass per experiment."""
    cm = oem.cm
    fns, _ = _stage_functions(oem, sum(d.n for d in oem.data), single=True)
    structure = (tuple(d.n for d in oem.data), tuple(map(tuple, oem.free_x0)))
    key = (*map(id, fns), structure)
    entry = _JACOBIANS.get(key)
    if entry is None or not all(a is b for a, b in zip(entry[0], fns)):
        pvec, pv = _data_blocks(oem)
        theta = ca.MX.sym("theta", oem.layout.size)
        out_fn, sens_fn, jrow_fn = fns
        w, r, jac, _, _ = _single_shooting_terms(oem, sens_fn, jrow_fn, out_fn, theta, pv)
        entry = (fns, ca.Function("condensed_jacobian", [w, pvec], [r, jac]))
        _JACOBIANS[key] = entry
        while len(_JACOBIANS) > SOLVER_CACHE_SIZE:
            _JACOBIANS.popitem(last=False)
    free = [np.array([x0s[e][cm.states[i]] / oem.xscale[i] for i in f]) for e, f in enumerate(oem.free_x0)]
    w0 = np.concatenate([np.asarray(theta_s, dtype=float).ravel(), *free])
    r, jac = entry[1](w0, _data_vector(oem))
    keep = np.concatenate([d.mask.T.ravel() for d in oem.data])     # sample-major, like r
    groups = np.concatenate([np.broadcast_to(np.arange(cm.ny), (d.n, cm.ny)).ravel() for d in oem.data])
    return np.array(jac)[keep], np.array(r).ravel()[keep], groups[keep]
