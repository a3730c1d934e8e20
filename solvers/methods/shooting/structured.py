"""Multiple shooting with a node at every sample, derivatives assembled from per-sample blocks.

CasADi's automatic Jacobian of the mapped continuity constraints spends most of a fit in the MX
virtual machine (≈150 ms per evaluation for 1000 samples of an 8-state model). Here every sample
contributes small blocks — ∂gap/∂x_k, ∂gap/∂θ, and the Gauss-Newton pieces J_kᵀr_k, J_kᵀJ_k of its
residual — computed by compiled, cached stage Functions; the sparse constraint Jacobian, the
gradient JᵀR and the Gauss-Newton Hessian JᵀJ are placed from those blocks (only their structural
nonzeros). Each NLP callback evaluates only what it returns (f and g at trial points need no
derivatives), and the stage Functions run BLOCK samples per call. Cost and memory grow linearly in
the record.

Single shooting is condensed (the sensitivities carried along one simulation); from
FOLD_MIN_SAMPLES samples on, its callbacks are no MX graph at all but `single_pass`'s: each one
compiled loop over all samples, the sensitivity pass once per point for grad_f and hess_l.

Data (inputs, times, measurements, weights, state scales) and the parameter layout enter the NLP
as parameters, so one Ipopt instance serves every fit of the same model structure and record
lengths: a worker builds it once and reuses it (`_SOLVERS`).
"""
from __future__ import annotations

import math
import os
import threading
import weakref
from collections import OrderedDict
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import casadi as ca
import numpy as np

from greyfit.solvers.dynamics import quick
from greyfit.solvers.dynamics.columns import Fold
from greyfit.solvers.dynamics.compiled import compiled, loaded
from greyfit.solvers.dynamics.compiled import mode as compile_mode
from greyfit.solvers.dynamics.integration import integrator_of
from greyfit.solvers.methods.shooting import handover, single_pass
from greyfit.solvers.nlp.problem import LeastSquaresProblem

EXPECTED_ITERATIONS = 20
SOLVER_CACHE_SIZE = 16
_SOLVERS: "OrderedDict[tuple, tuple]" = OrderedDict()
# Ipopt's CPU limit is fixed when its instance is made, and a retry (finer substeps, a cubic input
# reading, multiple shooting after single) gets the fit's CPU time left, a new value each time: its
# solver was built again on every request (10-30 ms of a 101-sample fit). The limit is floored to
# this grid (steps of 2^(1/8), 9 %) so that a structure keeps one instance; never above the limit asked.
CPU_LIMIT_STEPS_PER_OCTAVE = 8


def ipopt_cpu_limit(seconds: float) -> float:
    """The CPU limit an Ipopt instance is built with: `seconds` floored to a geometric grid.

    Parameters
    ----------
    seconds : float
        The CPU time the solve may take (the request's ``max_cpu_time``, or what a retry has left).

    Returns
    -------
    float
        The largest 2^(k / `CPU_LIMIT_STEPS_PER_OCTAVE`) (k an integer) at most `seconds`, so that
        retries whose budgets differ by a few milliseconds share one cached solver; `seconds`
        itself where it is not positive and finite.
    """
    if not (math.isfinite(seconds) and seconds > 0):
        return seconds
    k = CPU_LIMIT_STEPS_PER_OCTAVE
    return min(float(2.0 ** (math.floor(math.log2(seconds) * k + 1e-9) / k)), seconds)


def supports(oem, single: bool = False) -> bool:
    """Structured path: single shooting, or multiple shooting with a node at every sample; the
    Gauss-Newton Hessian; an SX step (RK4 or discrete).

    `GREYFIT_STRUCTURED_SHOOTING=0` forces the generic graph (for benchmarks and diagnosis).

    Parameters
    ----------
    oem : OutputErrorModel
        The output-error model (options, model and data).
    single : bool, optional
        True for single shooting (any node interval applies).

    Returns
    -------
    bool
        Whether the structured formulation applies (and every experiment has at least 2 samples).
    """
    opts = oem.options
    return (os.environ.get("GREYFIT_STRUCTURED_SHOOTING", "1") != "0"
            and (single or opts.shooting_interval == 1) and opts.hessian == "gauss_newton"
            and (integrator_of(opts).symbolic or oem.cm.model.discrete is not None)
            and all(d.n >= 2 for d in oem.data))


STAGES_MULTIPLE = ("step", "gap", "out", "gn")
STAGES_SINGLE = ("step_acc", "out", "sens_acc", "sgn")
# single shooting's folded callbacks (`single_pass`) from this many samples of a structure on; below,
# the MX graph of mapped blocks. A Python callback costs ~60 µs a call inside Ipopt, the graph's
# passes grow with the record: 2 states, warm CPU of a solve, folded / mapped: 101 samples 15.5 /
# 12.6 ms, 401: 10.6 / 10.5, 1001: 10.2 / 17.3, 4001: 22.7 / 75.3 (bench/bench_single_shooting.py)
FOLD_MIN_SAMPLES = 400
# samples per call of a compiled stage Function: CasADi's map costs ~0.2 µs per call, more than
# the whole work of a small model's sample (0.5 s of a 40 000-sample fit of a 2-state model)
BLOCK = 32


class _Stage:
    """A per-sample Function evaluated BLOCK samples per call (the record padded to whole blocks
    by repeating its last sample, the padding's outputs dropped)."""

    def __init__(self, single: ca.Function, block: ca.Function):
        self.single, self.block = single, block

    @staticmethod
    def _padded(args, count: int, widths: list[int]) -> tuple[list, int]:
        blocks = -(-count // BLOCK)
        pad = blocks * BLOCK - count
        if pad:   # a per-sample input has count·width columns, a shared one its width only
            args = [ca.horzcat(a, ca.repmat(a[:, -w:], 1, pad)) if a.size2() == count * w else a
                    for a, w in zip(args, widths)]
        return args, blocks

    def map(self, count: int, *args) -> list[ca.MX]:
        f = self.single
        padded, blocks = self._padded(args, count, [f.size2_in(i) for i in range(f.n_in())])
        outs = self.block.map(blocks, "serial")(*padded)
        outs = outs if isinstance(outs, (list, tuple)) else [outs]
        return [o[:, :count * f.size2_out(j)] if o.size2() != count * f.size2_out(j) else o
                for j, o in enumerate(outs)]

    def accum(self, count: int, x0, *args) -> ca.MX:
        """x_1 … x_count of x_k+1 = f(x_k, args_k) (`mapaccum`)."""
        f = self.single
        padded, blocks = self._padded(args, count, [f.size2_in(i) for i in range(1, f.n_in())])
        states = self.block.mapaccum("sim", blocks, [0], [0])(x0, *padded)[1]
        return states[:, :count] if states.size2() != count else states


def _blocks(fns: dict[str, ca.Function]) -> dict[str, ca.Function]:
    """BLOCK samples per call: `name` maps, `name_acc` accumulates a step (final state, all states)."""
    out = {}
    for name, fn in fns.items():
        ins = [ca.MX.sym(fn.name_in(i), fn.size1_in(i), BLOCK * fn.size2_in(i)) for i in range(fn.n_in())]
        res = fn.map(BLOCK, "serial")(*ins)
        res = list(res) if isinstance(res, (list, tuple)) else [res]
        out[name] = ca.Function(f"{fn.name()}_map{BLOCK}", ins, res)
        if name in ("step", "sens"):
            ins[0] = ca.MX.sym(fn.name_in(0), fn.sparsity_in(0))
            states = fn.mapaccum("sim", BLOCK)(*ins)
            out[f"{name}_acc"] = ca.Function(f"{fn.name()}_acc{BLOCK}", ins, [states[:, -1], states])
    return out


_FOLDS: "OrderedDict[int, Fold]" = OrderedDict()


def _single_folds(oem, samples: int) -> tuple[dict[str, Fold], bool]:
    """Single shooting's two kernels (`single_pass.build_kernels`) as folds, compiled where it pays
    (side by side when both are new: gcc runs outside the GIL); whether both are compiled C."""
    free = single_pass.free_states(oem)
    kernels = single_pass.kernels(oem, free)
    # trial points evaluate the cost about as often as accepted ones the sensitivities
    work = {"value": 2.0 * samples * EXPECTED_ITERATIONS, "sens": samples * EXPECTED_ITERATIONS}

    def fold(name: str) -> Fold:
        fn = kernels[name]
        known = _FOLDS.get(id(fn))
        # a fold that loaded its library before GREYFIT_COMPILE became "never" is not reused
        if known is not None and known.fn is fn and not (known.compiled and compile_mode() == "never"):
            _FOLDS.move_to_end(id(fn))
            known.find_library(work[name])
            return known
        made = _FOLDS[id(fn)] = Fold(fn, work[name], interpret_meanwhile=True,   # handover.py: never waits for gcc
                                     per_sample=single_pass.SENS_PER_SAMPLE if name == "sens" else ())
        while len(_FOLDS) > 2 * SOLVER_CACHE_SIZE:
            _FOLDS.popitem(last=False)
        return made

    new = [name for name in kernels if id(kernels[name]) not in _FOLDS]
    if len(new) > 1:
        with ThreadPoolExecutor(max_workers=len(new)) as pool:
            folds = dict(zip(new, pool.map(fold, new)))
    else:
        folds = {name: fold(name) for name in kernels}
    return folds, all(f.compiled for f in folds.values())


# block Functions whose compilation this process has started (held, so their ids stay theirs)
_TRIED: dict[int, ca.Function] = {}


def _stage_functions(oem, samples: int, names: tuple[str, ...]) -> tuple[dict[str, _Stage], bool, bool]:
    """The named stages (`_build_stages`), their blocks compiled C where it pays (`solvers.compiled`),
    and until gcc's libraries are built, the quick tier's where there is one and it pays (`quick`);
    whether every block is gcc's, and whether every block is C (gcc's or tcc's).

    Libraries a structure still needs are first compiled side by side (gcc runs outside the GIL):
    a first fit of seed 000's seat model waits for the largest, not for the sum.
    """
    o = oem.options
    pattern = single_pass.matrix_pattern(oem).get_triplet()
    fns, blocks = oem.cm.derive(("stages", o.integrator, o.substeps, o.input_interpolation, oem.layout.size,
                                 tuple(pattern[0]), tuple(pattern[1])),
                                lambda: (lambda f: (f, _blocks(f)))(_build_stages(oem)))

    def work(name: str) -> float:
        # `compiled` weighs instructions × evaluations: a block's wrapper counts a handful of calls
        return samples * EXPECTED_ITERATIONS * fns[name.removesuffix("_acc")].n_instructions() / \
            max(blocks[name].n_instructions(), 1)

    def build(name: str) -> tuple[ca.Function, bool]:
        ready = loaded(blocks[name])   # every fit after the first: a dictionary lookup
        if ready is not None:
            return ready, True
        return compiled(blocks[name], work(name), interpret_meanwhile=True)   # handover.py: never waits for gcc

    # until gcc's are built, tcc's stand in for all of them or none (an NLP half interpreted would
    # say neither), where their interpreted work together costs more than building them; built
    # first, so that gcc's background builds take their sources (`compiled.offer_source`)
    missing = [n for n in names if loaded(blocks[n]) is None and quick.goes_first(blocks[n])]
    single = [fns[n.removesuffix("_acc")].n_instructions() for n in missing]   # what tcc compiles
    stand_ins: dict[str, ca.Function | None] = {}
    if missing and quick.quick_compiler() is not None \
            and quick.pays(sum(single), sum(blocks[n].n_instructions() * work(n) for n in missing)):
        with ThreadPoolExecutor(max_workers=len(missing)) as pool:   # tcc runs outside the GIL
            stand_ins = dict(zip(missing, pool.map(lambda n: quick.quick_function(blocks[n]), missing)))

    new = [n for n in names if _TRIED.get(id(blocks[n])) is not blocks[n]]
    if len(new) > 1:
        with ThreadPoolExecutor(max_workers=len(new)) as pool:
            list(pool.map(build, new))
    if len(_TRIED) > 256:
        _TRIED.clear()
    _TRIED.update((id(blocks[n]), blocks[n]) for n in new)
    built = {name: build(name) for name in names}   # loaded by now: memory lookups
    final = all(is_c for _, is_c in built.values())
    waiting = [name for name, (_, is_c) in built.items() if not is_c]
    if waiting and all(stand_ins.get(n) is not None for n in waiting):
        built.update((n, (stand_ins[n], True)) for n in waiting)
    stages = {name: _Stage(fns[name.removesuffix("_acc")], fn) for name, (fn, _) in built.items()}
    return stages, final, all(is_c for _, is_c in built.values())


def _triu_pairs(n: int) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of the upper triangle of an n × n matrix, column by column (CasADi's order)."""
    cols, rows = np.nonzero(np.tril(np.ones((n, n), dtype=bool)))   # (j, i) with i <= j
    return rows, cols


def _build_stages(oem) -> dict[str, ca.Function]:
    """Per-sample Functions over scaled states x (x_phys = xs·x) and θ (p = off + M θ).

    Each callback of the NLP gets its own Function, so none computes what it throws away (Ipopt
    evaluates f and g at every trial point, the derivatives only at accepted ones):
    step (x_k -> x_k+1, the value of a gap and of a simulation), gap (its Jacobians in x_k and θ),
    out (weighted residual r_k with ∂r/∂x, ∂r/∂θ), gn (r_k with its Gauss-Newton pieces: the
    gradient J_kᵀr_k and J_kᵀJ_k of J_k = [∂r/∂x_k, ∂r/∂θ]), sens (x_k and S_k = ∂x_k/∂[θ, x0]
    -> x_k+1, S_k+1), sgn (the same pieces for single shooting's row J_k = ∂r/∂x S_k + [∂r/∂θ, 0]).
    Single shooting of long records folds its own kernels instead (`single_pass`), and the
    condensed Jacobian has its own row kernel (`single_pass.build_row_kernel`).
    """
    cm, nth = oem.cm, oem.layout.size
    nx, nv = cm.nx, nth + cm.nx
    sx = ca.SX.sym
    xk, xk1, xs = sx("xk", nx), sx("xk1", nx), sx("xs", nx)
    u0, u1, t0, dt = sx("u0", cm.nu), sx("u1", cm.nu), sx("t0"), sx("dt")
    theta, mat, off = sx("theta", nth), sx("M", cm.np, nth), sx("off", cm.np)
    y, wt = sx("y", cm.ny), sx("wt", cm.ny)
    p = off + ca.mtimes(ca.project(mat, single_pass.matrix_pattern(oem)), theta)   # as single_pass.build_kernels
    xn = oem.step(xs * xk, u0, u1, p, t0, dt) / xs
    fns = {}
    fns["step"] = ca.Function("greyfit_step", [xk, u0, u1, t0, dt, theta, mat, off, xs], [xn])
    gap = xn - xk1
    fns["gap"] = ca.Function("greyfit_gap", [xk, xk1, u0, u1, t0, dt, theta, mat, off, xs],
                             [gap, ca.jacobian(gap, xk), ca.jacobian(gap, theta)])
    r = wt * (cm.output(xs * xk, u0, p, t0) - y)
    rx, rt = ca.jacobian(r, xk), ca.jacobian(r, theta)
    out_in = [xk, u0, t0, theta, mat, off, xs, y, wt]
    fns["out"] = ca.Function("greyfit_out", out_in, [r, rx, rt])
    # the symbolic sparsity of these blocks (e.g. no θ in an output) is the NLP's Hessian pattern
    fns["gn"] = ca.Function("greyfit_gn", out_in, [
        r, ca.mtimes(rx.T, r), ca.mtimes(rt.T, r), ca.triu(ca.mtimes(rx.T, rx)),
        ca.mtimes(rt.T, rx), ca.mtimes(rt.T, rt)])
    sens = sx("S", nx, nv)
    s_next = ca.mtimes(ca.jacobian(xn, xk), sens) + ca.horzcat(ca.jacobian(xn, theta), ca.SX(nx, nx))
    z = ca.vertcat(xk, ca.vec(sens))
    fns["sens"] = ca.Function("greyfit_sens", [z, u0, u1, t0, dt, theta, mat, off, xs],
                              [ca.vertcat(xn, ca.vec(s_next))])
    jrow = ca.mtimes(rx, sens) + ca.horzcat(rt, ca.SX(cm.ny, nx))
    fns["sgn"] = ca.Function("greyfit_sgn", [z, u0, t0, theta, mat, off, xs, y, wt],
                             [r, ca.mtimes(jrow.T, r), ca.vec(ca.mtimes(jrow.T, jrow))])
    return fns


class _Blocks:
    """Named blocks of one parameter vector (the data)."""

    def __init__(self) -> None:
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


def _stacked(sp: ca.Sparsity, count: int, row0: int, col0: int, row_step: int, col_step: int):
    """(rows, cols) of the nonzeros of `count` blocks of pattern `sp` stored side by side (a mapped
    output), in nonzero order: block k covers rows row0 + k·row_step … and columns
    col0 + k·col_step … (step nx for the nodes of sample k, 0 for the θ every block shares).

    Only the structural nonzeros of the stage Function's output enter the NLP: an output that no
    θ affects leaves no θ-node entries in the Hessian for MUMPS to arrange and factorise.
    """
    r, c = (np.array(v, dtype=int) for v in sp.get_triplet())
    k = np.repeat(np.arange(count), r.size)
    return row0 + k * row_step + np.tile(r, count), col0 + k * col_step + np.tile(c, count)


def _nonzeros(m: ca.MX) -> ca.MX:
    """The nonzeros of `m` as a column (a row vector's would come as a row)."""
    return ca.reshape(m.nz[:], m.nnz(), 1)


def _sparse(nrow: int, ncol: int, rows: np.ndarray, cols: np.ndarray, values: ca.MX) -> ca.MX:
    """MX sparse matrix from triplets (no duplicates); `values` in triplet order."""
    order = np.lexsort((rows, cols))   # CasADi stores column-major
    sp = ca.Sparsity.triplet(nrow, ncol, rows[order].tolist(), cols[order].tolist())
    return ca.MX(sp, values[order.tolist()])


@dataclass
class _Nlp:
    solver: ca.Function
    keep: tuple = ()   # the Python callbacks the solver calls (alive as long as it is)


@dataclass
class _Terms:
    """The data part of one formulation, each piece for the callback that needs it.

    f = ½‖r‖², for f (trial points); f_gn, grad = Jᵀr, hess = triu(JᵀJ): from the Gauss-Newton
    stage Functions, for grad_f and the Hessian; gaps (value) for g; jac_gap with its own gaps for
    jac_g.
    """
    w: ca.MX
    f: ca.MX
    f_gn: ca.MX
    grad: ca.MX
    hess: ca.MX
    gaps: ca.MX
    gaps_jac: ca.MX
    jac_gap: ca.MX


def _data_blocks(oem) -> tuple[ca.MX, dict[str, ca.MX]]:
    """The data parameter vector and its named views (layout of `_data_vector`)."""
    pb = _data_layout(oem)
    pvec = ca.MX.sym("data", pb.size)
    return pvec, pb.views(pvec)


def _folded_blocks(oem) -> tuple[ca.MX, dict[str, ca.MX]]:
    """The folded NLP's own parameter vector and its views: only what its MX graph reads (the
    parameter map and offset, for the constraints) and the record's token last. The record goes to
    the callbacks by its token (`SinglePass.attach`), not through Ipopt: CasADi copies an NLP's
    parameters into every function evaluation (56 ms per solve for 600 000 numbers, and 77 ms of a
    400 ms fit of 200 000 samples)."""
    pb = _folded_layout(oem)
    pvec = ca.MX.sym("data", pb.size + 1)
    return pvec, pb.views(pvec)


def _folded_layout(oem) -> _Blocks:
    pb = _Blocks()
    for e in range(len(oem.data)):
        pb.add(f"M{e}", oem.cm.np, oem.layout.size)
    pb.add("off", oem.cm.np, 1)
    return pb


def _folded_vector(oem, token: float) -> np.ndarray:
    """The values of `_folded_blocks`."""
    parts = [oem.layout.matrix[e].ravel(order="F") for e in range(len(oem.data))]
    return np.concatenate([np.asarray(p, dtype=float).ravel() for p in [*parts, oem.layout.offset, [token]]])


def _data_layout(oem) -> _Blocks:
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
    return pb


def _multiple_shooting_terms(oem, fns: dict[str, _Stage], theta, pv) -> _Terms:
    """Nodes at every sample; the blocks placed in sparse matrices.

    Hessian triu(JᵀJ), J = ∂r/∂[θ, nodes]: r_k depends on node k and θ only, so JᵀJ is a
    node-node block per sample, a θ-node block per sample and a θθ block summed over samples.
    """
    nx, nth = oem.cm.nx, oem.layout.size
    gap_sp, gn_sp = fns["gap"].single.sparsity_out, fns["gn"].single.sparsity_out
    nodes = [ca.MX.sym(f"X{e}", nx, d.n) for e, d in enumerate(oem.data)]
    w = ca.vertcat(theta, *[ca.vec(X) for X in nodes])
    off, xs = pv["off"], pv["xs"]
    gaps, gaps_jac, r_parts, r_gn, grad_x = [], [], [], [], []
    grad_t, h_tt = ca.MX(nth, 1), ca.MX(nth * nth, 1)
    g_rows, g_cols, g_vals = [], [], []
    h_rows, h_cols, h_vals = [], [], []
    row_g = 0
    col = nth
    for e, d in enumerate(oem.data):
        n, m = d.n, d.n - 1
        X, U, T, Y, W, M = nodes[e], pv[f"U{e}"], pv[f"T{e}"], pv[f"Y{e}"], pv[f"W{e}"], pv[f"M{e}"]
        DT = T[:, 1:] - T[:, :-1]
        xn, = fns["step"].map(m, X[:, :-1], U[:, :-1], U[:, 1:], T[:, :-1], DT, theta, M, off, xs)
        gaps.append(ca.vec(xn - X[:, 1:]))
        G, GX, GT = fns["gap"].map(m, X[:, :-1], X[:, 1:], U[:, :-1], U[:, 1:], T[:, :-1], DT,
                                   theta, M, off, xs)
        gaps_jac.append(ca.vec(G))
        out_args = (X, U, T, theta, M, off, xs, Y, W)
        r_parts.append(ca.vec(fns["out"].map(n, *out_args)[0]))
        R, GXR, GTR, HXX, HTX, HTT = fns["gn"].map(n, *out_args)
        r_gn.append(ca.vec(R))
        grad_x.append(ca.vec(GXR))
        grad_t += ca.sum2(GTR)
        h_tt += ca.sum2(ca.reshape(HTT, nth * nth, n))
        # ∂gap_k/∂x_k, ∂gap_k/∂θ, ∂gap_k/∂x_k+1 = −I
        for rows, cols in (_stacked(gap_sp(1), m, row_g, col, nx, nx),
                           _stacked(gap_sp(2), m, row_g, 0, nx, 0),
                           _stacked(ca.Sparsity.diag(nx), m, row_g, col + nx, nx, nx)):
            g_rows.append(rows)
            g_cols.append(cols)
        g_vals += [_nonzeros(GX), _nonzeros(GT), ca.MX(ca.DM(-np.ones(m * nx)))]
        # node-node upper triangles, then the θ rows of the node columns (θ comes first in w)
        for rows, cols in (_stacked(gn_sp(3), n, col, col, nx, nx),
                           _stacked(gn_sp(4), n, 0, col, 0, nx)):
            h_rows.append(rows)
            h_cols.append(cols)
        h_vals += [_nonzeros(HXX), _nonzeros(HTX)]
        row_g += m * nx
        col += n * nx
    t_r, t_c = _triu_pairs(nth)
    h_rows.append(t_r)
    h_cols.append(t_c)
    h_vals.append(ca.densify(h_tt)[(t_c * nth + t_r).tolist()])
    nw = w.numel()
    jac_gap = _sparse(row_g, nw, np.concatenate(g_rows), np.concatenate(g_cols), ca.vertcat(*g_vals))
    hess = _sparse(nw, nw, np.concatenate(h_rows), np.concatenate(h_cols), ca.vertcat(*h_vals))
    return _Terms(w, 0.5 * ca.sumsqr(ca.vertcat(*r_parts)), 0.5 * ca.sumsqr(ca.vertcat(*r_gn)),
                  ca.vertcat(grad_t, *grad_x), hess, ca.vertcat(*gaps), ca.vertcat(*gaps_jac), jac_gap)


def _free_x0(oem, e: int, pv, free: list[ca.MX]) -> ca.MX:
    """Scaled x0 of experiment e: the known entries from the data, the free ones from w."""
    nx = oem.cm.nx
    place = np.zeros((nx, len(oem.free_x0[e])))
    place[oem.free_x0[e], np.arange(len(oem.free_x0[e]))] = 1.0
    return pv[f"X0{e}"] + ca.mtimes(ca.DM(place), free[e])   # the data block is 0 where x0 is free


# the `SinglePass` of each folded structure, shared by its NLPs (one per iteration limit, the
# multistart's and the hybrid's): a point one of them evaluated is known to all (the start checks'
# pass at the guess is the solve's first); the entry holds its folds, so their ids stay theirs
_PASSES: "OrderedDict[tuple, tuple[tuple, single_pass.SinglePass]]" = OrderedDict()


def _single_pass(oem, folds: dict[str, Fold]) -> single_pass.SinglePass:
    owners = tuple(fold.fn for fold in folds.values())
    key = (*map(id, owners), tuple(d.n for d in oem.data), tuple(map(tuple, oem.free_x0)), oem.layout.size)
    entry = _PASSES.get(key)
    if entry is not None and all(a is b for a, b in zip(entry[0], owners)):
        _PASSES.move_to_end(key)
        return entry[1]
    sp = single_pass.SinglePass(oem, folds, _data_layout(oem).shapes, single_pass.free_states(oem))
    _PASSES[key] = (owners, sp)
    while len(_PASSES) > SOLVER_CACHE_SIZE:
        _PASSES.popitem(last=False)
    return sp


def _token_record(oem) -> tuple[float, np.ndarray]:
    """(token, the data vector with the token last) of this model's record: one token per model, so
    every solver of it shares its points."""
    if oem.single_pass_token is None:
        oem.single_pass_token = single_pass.new_token()
        # what the passes bound to this token goes with the model (its fit), not when later fits push it out
        weakref.finalize(oem, _forget_token, oem.single_pass_token)
    return oem.single_pass_token, np.append(_data_vector(oem), oem.single_pass_token)


def _forget_token(token: float) -> None:
    # a finalizer: `forget` only queues; the cache may change under us in another thread's hands
    try:
        passes = list(_PASSES.values())
    except RuntimeError:   # changed while read: its passes drop the token when it is next seen
        return
    for _, sp in passes:
        sp.forget(token)


def _single_shooting_terms(oem, folds: dict[str, Fold], theta, pv, pvec) -> tuple[_Terms, tuple]:
    """No gaps and no MX graph of the samples: f, grad_f and the Hessian are callbacks of one
    `single_pass.SinglePass`, each one folded compiled loop (the derivatives one pass per point).
    Also returns the callbacks, which must live as long as the solver."""
    sp = _single_pass(oem, folds)
    cbs = single_pass.callbacks(sp)
    w = ca.vertcat(theta, ca.MX.sym("x0", sp.nw - sp.nth))
    token = pvec[-1]
    f_gn, grad = cbs["grad"](w, token)
    terms = _Terms(w, cbs["cost"](w, token), f_gn, grad, cbs["hess"](w, token),
                   ca.MX(0, 1), ca.MX(0, 1), ca.MX(0, sp.nw))
    return terms, (sp, *cbs.values())


def _mapped_single_shooting_terms(oem, fns: dict[str, _Stage], theta, pv) -> _Terms:
    """No gaps: one simulation per experiment for f, one carrying the sensitivities S_k =
    ∂x_k/∂[θ, x0] (the nodes of multiple shooting condensed away) for the derivatives, whose
    per-sample rows J_k = ∂r_k/∂x S_k + [∂r_k/∂θ, 0] reduce to J_kᵀr_k and J_kᵀJ_k in C."""
    nx, nth = oem.cm.nx, oem.layout.size
    nv = nth + nx
    free = [ca.MX.sym(f"x0_{e}", len(f)) for e, f in enumerate(oem.free_x0)]
    w = ca.vertcat(theta, *free)
    nw = w.numel()
    off, xs = pv["off"], pv["xs"]
    seed = np.vstack([np.zeros((nth, nx)), np.eye(nx)]).T.ravel(order="F")   # S_0 = [0 | I]
    r_parts, r_gn = [], []
    grad, hess = ca.MX(nw, 1), ca.MX(nw, nw)
    col = nth
    for e, d in enumerate(oem.data):
        U, T, Y, W, M = pv[f"U{e}"], pv[f"T{e}"], pv[f"Y{e}"], pv[f"W{e}"], pv[f"M{e}"]
        DT = T[:, 1:] - T[:, :-1]
        x0 = _free_x0(oem, e, pv, free)
        X = fns["step_acc"].accum(d.n - 1, x0, U[:, :-1], U[:, 1:], T[:, :-1], DT, theta, M, off, xs)
        X = ca.horzcat(x0, X)
        r_parts.append(ca.vec(fns["out"].map(d.n, X, U, T, theta, M, off, xs, Y, W)[0]))
        z0 = ca.vertcat(x0, ca.DM(seed))
        Z = fns["sens_acc"].accum(d.n - 1, z0, U[:, :-1], U[:, 1:], T[:, :-1], DT, theta, M, off, xs)
        R, G, H = fns["sgn"].map(d.n, ca.horzcat(z0, Z), U, T, theta, M, off, xs, Y, W)
        r_gn.append(ca.vec(R))
        # [θ, x0] of this experiment -> w: θ, and its free x0 entries at their columns
        place = np.zeros((nw, nv))
        place[np.arange(nth), np.arange(nth)] = 1.0
        for j, i in enumerate(oem.free_x0[e]):
            place[col + j, nth + i] = 1.0
        col += len(oem.free_x0[e])
        place = ca.DM(ca.sparsify(ca.DM(place)))
        grad += ca.mtimes(place, ca.sum2(G))
        hess += ca.mtimes([place, ca.reshape(ca.sum2(H), nv, nv), place.T])
    return _Terms(w, 0.5 * ca.sumsqr(ca.vertcat(*r_parts)), 0.5 * ca.sumsqr(ca.vertcat(*r_gn)), grad,
                  ca.triu(hess), ca.MX(0, 1), ca.MX(0, 1), ca.MX(0, nw))


def _build_nlp(oem, terms: _Terms, theta, pvec, pv, penalty, max_iter: int, max_cpu_time: float,
               keep: tuple = ()) -> _Nlp:
    """The Ipopt instance over the terms plus the user's parameter constraints and a penalty on θ;
    `keep`: the Python callbacks it calls."""
    cm, nth = oem.cm, oem.layout.size
    w = terms.w
    nw = w.numel()
    g_par = []
    if cm.constraint is not None:
        for e in range(_constraint_copies(oem)):
            g_par.append(cm.constraint(pv["off"] + ca.mtimes(pv[f"M{e}"], theta)))
    g_par = ca.vertcat(*g_par) if g_par else ca.MX(0, 1)
    jac_par = ca.horzcat(ca.jacobian(g_par, theta), ca.MX(g_par.numel(), nw - nth))
    f, f_gn = terms.f, terms.f_gn
    grad, hess = terms.grad, terms.hess
    if penalty is not None:
        pen = penalty(theta)
        jp = ca.jacobian(pen, theta)
        f, f_gn = f + 0.5 * ca.sumsqr(pen), f_gn + 0.5 * ca.sumsqr(pen)
        grad = grad + ca.vertcat(ca.mtimes(jp.T, pen), ca.MX(nw - nth, 1))
        hess = hess + ca.diagcat(ca.triu(ca.mtimes(jp.T, jp)), ca.MX(nw - nth, nw - nth))
    g = ca.vertcat(terms.gaps, g_par)
    sigma, lam_g = ca.MX.sym("sigma"), ca.MX.sym("lam_g", g.numel())
    names_xp = ["x", "p"]
    # dense: Ipopt's interface copies the gradient's nonzeros as they come (a θ that no output
    # depends on leaves structural zeros, and stale memory in their place)
    grad_f = ca.Function("nlp_grad_f", [w, pvec], [f_gn, ca.densify(grad)], names_xp, ["f", "grad_f_x"])
    jac_g_fn = ca.Function("nlp_jac_g", [w, pvec], [ca.vertcat(terms.gaps_jac, g_par),
                                                   ca.vertcat(terms.jac_gap, jac_par)],
                           names_xp, ["g", "jac_g_x"])
    hess_fn = ca.Function("nlp_hess_l", [w, pvec, sigma, lam_g], [sigma * hess],
                          ["x", "p", "lam_f", "lam_g"], ["hess_gamma_x_x"])
    opts = oem.options
    solver = ca.nlpsol("greyfit_structured", "ipopt", {"x": w, "p": pvec, "f": f, "g": g}, {
        "grad_f": grad_f, "jac_g": jac_g_fn, "hess_lag": hess_fn,
        "ipopt.max_iter": max_iter, "ipopt.max_cpu_time": max_cpu_time, "ipopt.tol": opts.tol,
        # QAMD ordering copes with the dense θ columns: the automatic choice spent 8 s of 10 in
        # MUMPS' analysis at 40 000 samples (2 states), QAMD 0.3 s
        "ipopt.mumps_pivot_order": 6,
        # MUMPS' work space: Ipopt's default (1000 % over MUMPS' estimate) is allocated and cleared
        # at every factorisation, ~8000 fresh pages (30 ms of 250) per fit of seed 000's seat model
        "ipopt.mumps_mem_percent": 100,
        # the Gauss-Newton Hessian ignores the multipliers: their least-squares estimate at the start
        # cost a factorisation and changed no step
        "ipopt.constr_mult_init_max": 0.0,
        # a refinement of every step whether or not its residual asks for one: a back-solve per
        # iteration; Ipopt still refines a step whose residual exceeds residual_ratio_max
        "ipopt.min_refinement_steps": 0,
        # single shooting starts the barrier at 1e-3, not 0.1: Ipopt scales the objective to gradients
        # of O(100), where a least-squares cost near its optimum is O(1) or less, and the default
        # barrier bent the first steps and took iterations to wind down (the seat model 9 → 7 or
        # 11 → 8, the 101-sample oscillator 5 → 4; the same optima to tol). `auto` runs single
        # shooting only where the simulation at the guess is sane; multiple shooting, for rough starts
        # and unstable models, keeps Ipopt's default
        **({"ipopt.mu_init": 1e-3} if terms.gaps.numel() == 0 else {}),
        "ipopt.print_level": 0, "ipopt.sb": "yes", "print_time": False, "show_eval_warnings": False,
        # nor the gradient of the Lagrangian CasADi builds for multipliers nobody reads: its
        # reverse mode through the compiled blocks ran finite differences for 17 s
        "calc_lam_p": False, "calc_multipliers": False, "no_nlp_grad": True})
    return _Nlp(solver, keep)


def _data_vector(oem) -> np.ndarray:
    """The NLP's parameter vector: the record, weights, parameter map and scales (fixed for the
    model of one fit, which asks for it for its solver and for each condensed Jacobian)."""
    if oem.structured_data is None:
        oem.structured_data = _assemble_data_vector(oem)
    return oem.structured_data


def _assemble_data_vector(oem) -> np.ndarray:
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

    def __init__(self, nlp: _Nlp, data: np.ndarray, problem: LeastSquaresProblem, compiled_c: bool,
                 upgrade=None, record: np.ndarray | None = None, final: bool = True):
        """`data`: the NLP's parameter values; `compiled_c`: its per-sample code is C (gcc's, or the
        quick tier's tcc); `final`: it is gcc's; `upgrade`: makes this solver again (on gcc's code,
        once the libraries built meanwhile exist); `record`: the data vector with its token, for the
        folded callbacks (`SinglePass.attach`)."""
        self.nlp, self.data, self.problem, self.compiled = nlp, data, problem, compiled_c
        self.final = final
        self.upgrade, self.record = upgrade, record
        self._attach()

    def _attach(self) -> None:
        """The record to the folded callbacks, under the token that `data` ends with."""
        if self.record is not None:
            passes = [k for k in self.nlp.keep if isinstance(k, single_pass.SinglePass)]
            passes[0].attach(self.record)

    def solve(self, w0: np.ndarray, lbw: np.ndarray | None = None, ubw: np.ndarray | None = None):
        """Run Ipopt on the structured NLP from `w0`.

        Parameters
        ----------
        w0 : numpy.ndarray
            Start of the decision vector (scaled).
        lbw, ubw : numpy.ndarray, optional
            Bounds on the decision vector; None keeps the problem's.

        Returns
        -------
        NlpOutcome
            Ipopt's outcome. An NLP interpreted while its libraries are built moves to compiled
            code before a solve begins once they exist, never during one (`handover`): the same
            numbers either way.
        """
        from greyfit.solvers.nlp.solver import run_ipopt

        better = handover.built_meanwhile(self.final, self.upgrade)
        if better is not None:   # this solve and the next ones run gcc's code
            self.nlp, self.compiled, self.final, self.upgrade = better.nlp, True, True, None
        self._attach()   # again: other solvers of this structure may have attached theirs since
        return run_ipopt(self.nlp.solver, w0, self.problem, p=self.data, lbw=lbw, ubw=ubw)


def _constraint_copies(oem) -> int:
    if oem.cm.constraint is None:
        return 0
    return 1 if all(ex is None for ex in oem.layout.experiment) else len(oem.data)


def constraint_count(oem) -> int:
    """Rows of the model's parameter constraints in the structured NLP.

    Parameters
    ----------
    oem : OutputErrorModel
        The output-error model (its compiled model's constraint, layout and data).

    Returns
    -------
    int
        0 without a constraint; else its rows, once, or once per experiment when a parameter is per experiment.
    """
    return _constraint_copies(oem) * (oem.cm.constraint_equality.size if oem.cm.constraint is not None else 0)


def constraint_lower(oem) -> np.ndarray:
    """Lower bounds of the parameter-constraint rows.

    Parameters
    ----------
    oem : OutputErrorModel
        The output-error model (its compiled model's constraint, layout and data).

    Returns
    -------
    numpy.ndarray
        Zeros, shape (`constraint_count(oem)`,).
    """
    return np.zeros(constraint_count(oem))


def constraint_upper(oem) -> np.ndarray:
    """Upper bounds of the parameter-constraint rows: 0 for an equality, +inf for an inequality.

    Parameters
    ----------
    oem : OutputErrorModel
        The output-error model (its compiled model's constraint, layout and data).

    Returns
    -------
    numpy.ndarray
        Shape (`constraint_count(oem)`,); empty without a constraint.
    """
    if oem.cm.constraint is None:
        return np.zeros(0)
    return np.tile(np.where(oem.cm.constraint_equality, 0.0, np.inf), _constraint_copies(oem))


def attach_solver(oem, problem: LeastSquaresProblem, single: bool = False) -> LeastSquaresProblem:
    """Give `problem` (bounds, guesses and readers of single or multiple shooting) the structured
    solver, made when first asked for (after a time-varying penalty may have been attached).

    Parameters
    ----------
    oem : OutputErrorModel
        The output-error model.
    problem : LeastSquaresProblem
        The problem with its bounds, initial guess and readers; changed in place.
    single : bool, optional
        True for single shooting, False for multiple shooting with a node at every sample.

    Returns
    -------
    LeastSquaresProblem
        `problem`, its `solver_factory` set to make a (cached) `StructuredSolver`; the factory takes
        optional ``max_iter`` and ``max_cpu_time`` in place of the request's.
    """
    samples = sum(d.n for d in oem.data)
    structure = (single, tuple(d.n for d in oem.data), tuple(map(tuple, oem.free_x0)))
    o = oem.options
    folded = single and samples >= FOLD_MIN_SAMPLES

    def make_solver(max_iter: int | None = None, max_cpu_time: float | None = None):
        """`max_iter`, `max_cpu_time`: instead of the request's (a phase of a hybrid solve)."""
        iters = o.max_iter if max_iter is None else max_iter
        cpu = ipopt_cpu_limit(o.max_cpu_time if max_cpu_time is None else max_cpu_time)
        folds: dict[str, Fold] = {}
        stages: dict[str, _Stage] = {}
        if folded:   # the folds move from a stand-in to gcc's loops by themselves: never remade
            folds, runs_c = _single_folds(oem, samples)
            is_c = True
            owners = (*(fold.fn for fold in folds.values()), oem.cm.constraint)
        else:
            stages, is_c, runs_c = _stage_functions(oem, samples, STAGES_SINGLE if single else STAGES_MULTIPLE)
            owners = (*(st.block for st in stages.values()), oem.cm.constraint)
        penalty = problem.penalty
        # the stage Functions (and the constraint) identify the model structure, the rest shapes
        # the NLP; the entry holds those objects, so an id is never reused while it is cached. One
        # NLP per thread: an Ipopt instance and its Python callbacks called from two threads at once
        # crashed the process (fits of one structure in a thread pool; CasADi releases the GIL)
        nlp_key = (*map(id, owners), structure, iters, cpu, o.tol, threading.get_ident())
        entry = _SOLVERS.get(nlp_key) if penalty is None else None
        if entry is not None and all(a is b for a, b in zip(entry[0], owners)):
            _SOLVERS.move_to_end(nlp_key)
            nlp = entry[1]
        else:
            pvec, pv = _folded_blocks(oem) if folded else _data_blocks(oem)
            theta = ca.MX.sym("theta", oem.layout.size)
            keep: tuple = ()
            if folded:   # the folds switch to their compiled loops by themselves when built (the same numbers)
                terms, keep = _single_shooting_terms(oem, folds, theta, pv, pvec)
            else:
                build = _mapped_single_shooting_terms if single else _multiple_shooting_terms
                terms = build(oem, stages, theta, pv)
            nlp = _build_nlp(oem, terms, theta, pvec, pv, penalty, iters, cpu, keep)
            if penalty is None:
                _SOLVERS[nlp_key] = (owners, nlp)
                while len(_SOLVERS) > SOLVER_CACHE_SIZE:
                    _SOLVERS.popitem(last=False)
        upgrade = None if is_c else (lambda: make_solver(max_iter, max_cpu_time))
        if folded:   # the token under which the callbacks find this record and cache its points
            token, record = _token_record(oem)
            return StructuredSolver(nlp, _folded_vector(oem, token), problem, runs_c, upgrade, record, final=True)
        return StructuredSolver(nlp, _data_vector(oem), problem, runs_c, upgrade, final=is_c)

    def start_gram(w: np.ndarray) -> np.ndarray:
        """JᵀJ at w (scaled [θ, free x0]) by the sensitivity pass the solve's first evaluation at w
        then finds done (the structure's shared `SinglePass`, the model's token)."""
        folds, _ = _single_folds(oem, samples)
        sp = _single_pass(oem, folds)
        token, record = _token_record(oem)   # the record stays alive until the pass has bound it
        sp.attach(record)
        _, _, hess = sp.derivatives(np.asarray(w, dtype=float), np.array([token]))
        rows, cols = (np.asarray(a, dtype=int) for a in sp.hess_sparsity.get_triplet())
        gram = np.zeros((sp.nw, sp.nw))
        gram[rows, cols] = hess
        return gram + np.triu(gram, 1).T

    problem.solver_factory = make_solver
    if folded:
        problem.start_gram = start_gram
    return problem


def condensed_jacobian(oem, theta_s: np.ndarray, x0s: list[dict[str, float]],
                       w: np.ndarray | None = None):
    """(J, r, output of each row) of the single-shooting residual w.r.t. [θ, free x0] (scaled), at
    the measured samples: `shooting.sensitivity_jacobian` by one pass of the row kernel per experiment
    (`single_pass.condensed_rows`), compiled C once its library is built, CasADi's interpreter until
    then. (An MX graph of mapped blocks used to stand in until the library was ready: building it
    cost a seat model's first fit 64 ms, and a warm interpreted seat fit took 12 % longer with it.)

    Parameters
    ----------
    oem : OutputErrorModel
        The output-error model.
    theta_s : numpy.ndarray
        The scaled free parameters, shape (n θ,).
    x0s : list of dict
        Per experiment, state name -> initial value (physical units).
    w : numpy.ndarray or None, optional
        The single-shooting solve's decision vector at this point, when it is the solve's optimum:
        its last sensitivity pass ran there and wrote the rows, so no pass runs again.

    Returns
    -------
    jac : numpy.ndarray
        Jacobian of the weighted residual, shape (measured samples × outputs, n θ + free initial states).
    res : numpy.ndarray
        The weighted residual at the measured samples, sample-major.
    groups : numpy.ndarray
        The output index of each row.
    """
    if w is not None and oem.single_pass_token is not None:
        for _, sp in list(_PASSES.values()):
            parts = sp.rows_at(w, oem.single_pass_token)
            if parts is not None and len(parts) == len(oem.data):
                return single_pass.remember_rows(oem, theta_s, x0s, single_pass.assemble_rows(oem, parts))
    return single_pass.condensed_rows(oem, theta_s, x0s)
