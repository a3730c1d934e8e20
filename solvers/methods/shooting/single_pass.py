"""Single shooting's NLP callbacks, each one compiled loop over the samples.

The MX graph of mapped blocks that single shooting was built from cost 6–13× the compiled work it
wrapped, and its `grad_f` and `hess_l` callbacks each re-ran the sensitivity pass (43 + 46 of
122 ms on seed 000's seat model). Here each callback is a `ca.Callback` over numpy buffers that
runs one folded kernel (`columns.Fold`: the compiled library's loop over all samples):

- f, at every trial point: the simulation with the cost summed in the loop, no sensitivities;
- grad_f and hess_l, at accepted points: one pass carrying the sensitivities S_k = ∂x_k/∂[θ, x0]
  that sums J_kᵀr_k and triu(J_kᵀJ_k) of each row J_k = ∂r_k/∂x S_k + [∂r_k/∂θ, 0] in the loop.
  Its result is cached on the point, so the Hessian callback that follows the gradient's at the
  same point reads it.

The last entry of the NLP's parameter vector is a token unique to the data of one solver
(`StructuredSolver`): the record laid out per sample is cached under it, and so is the point
(w and token), so one Ipopt instance still serves every fit of the same structure.

A Python callback costs ~60 µs a call inside Ipopt, which short records do not repay:
`structured.FOLD_MIN_SAMPLES` says from which length on single shooting takes this path. Solve CPU
against the mapped graph, same optimum (bench/bench_single_shooting.py, a loaded 2-core machine):
seed 000's seat model 110 against 295 ms, 2 states × 40 000 samples 125 against 762 ms.
"""
from __future__ import annotations

import itertools
import threading
import weakref
from collections import OrderedDict, deque

import casadi as ca
import numpy as np

from greyfit.solvers.dynamics.columns import Fold
from greyfit.solvers.methods.shooting.later_drops import LaterDrops

_TOKENS = itertools.count(1)


def new_token() -> float:
    """A number no other solver's data of this process carries (the cache key of its record).

    Returns
    -------
    float
        The next token, exactly representable.
    """
    return float(next(_TOKENS))


def free_states(oem) -> tuple[int, ...]:
    """The states whose initial value some experiment estimates (the sensitivities' x0 columns).

    Parameters
    ----------
    oem : OutputErrorModel
        The output-error model (its free initial states per experiment).

    Returns
    -------
    tuple of int
        Sorted state indices.
    """
    return tuple(sorted({int(i) for f in oem.free_x0 for i in f}))


def matrix_pattern(oem) -> ca.Sparsity:
    """Where any experiment's parameter map M (p = off + M θ) is nonzero: the kernels use M with this
    sparsity, not dense (a dense symbolic M differentiated every parameter direction through every
    entry of p: 18 % of the seat model's sensitivity kernel's operations, 16 % of a 2-state one's).

    Parameters
    ----------
    oem : OutputErrorModel
        The output-error model (its parameter layout's maps, one per experiment).

    Returns
    -------
    casadi.Sparsity
        np × nθ.
    """
    layout = oem.layout
    used = np.zeros((oem.cm.np, layout.size), dtype=bool)
    for m in layout.matrix:
        used |= np.asarray(m) != 0
    rows, cols = np.nonzero(used)
    return ca.Sparsity.triplet(oem.cm.np, layout.size, rows.tolist(), cols.tolist())


def kernel_key(oem, free: tuple[int, ...]) -> tuple:
    """What single shooting's kernels are built from beyond the model: the integrator settings, the
    number of parameters, the free initial states and M's pattern (`matrix_pattern`).

    Parameters
    ----------
    oem : OutputErrorModel
        The output-error model.
    free : tuple of int
        The states whose initial value is estimated somewhere (`free_states`).

    Returns
    -------
    tuple
        Hashable.
    """
    o = oem.options
    rows, cols = matrix_pattern(oem).get_triplet()
    return (o.integrator, o.substeps, o.input_interpolation, oem.layout.size, free, tuple(rows), tuple(cols))



def build_kernels(oem, free: tuple[int, ...]) -> dict[str, ca.Function]:
    """The two per-sample kernels over scaled states x (x_phys = xs·x) and θ (p = off + M θ).

    `value`: (x_k, inputs) -> (x_k+1, ½‖r_k‖²); `sens`: ((x_k, vec S_k), inputs) ->
    ((x_k+1, vec S_k+1), ½‖r_k‖², J_kᵀr_k, triu(J_kᵀJ_k), r_k, J_k), S_k = ∂x_k/∂[θ, x0 of the
    `free` states] (a known initial state needs no direction: the seat model's 8 known x0 would
    double the work), J_k = ∂r_k/∂x S_k + [∂r_k/∂θ, 0] dense (ny × (nθ + free)). Outputs 1–3 are
    summed over the samples, r_k and J_k kept per sample (`SENS_PER_SAMPLE`): the pass at the
    solve's last point is the condensed Jacobian the fit's checks read at the optimum. Inputs after
    the state: u_k, u_k+1, t_k, t_k+1 − t_k, θ, M, off, xs, y_k, wt_k (the last sample's step is
    computed and dropped).

    Parameters
    ----------
    oem : OutputErrorModel
        The output-error model (its compiled model, step and parameter layout).
    free : tuple of int
        The states whose initial value is estimated somewhere (`free_states`).

    Returns
    -------
    dict of str to casadi.Function
        ``{"value": ..., "sens": ...}``, SX Functions.
    """
    cm, nth = oem.cm, oem.layout.size
    nx, nf = cm.nx, len(free)
    nv = nth + nf
    sx = ca.SX.sym
    xk, xs = sx("xk", nx), sx("xs", nx)
    u0, u1, t0, dt = sx("u0", cm.nu), sx("u1", cm.nu), sx("t0"), sx("dt")
    theta, mat, off = sx("theta", nth), sx("M", cm.np, nth), sx("off", cm.np)
    y, wt = sx("y", cm.ny), sx("wt", cm.ny)
    # M's entries outside its pattern are structural zeros: θ_j's direction then enters p only where
    # it acts (the input stays dense; its other entries are zero and never read)
    p = off + ca.mtimes(ca.project(mat, matrix_pattern(oem)), theta)
    xn = oem.step(xs * xk, u0, u1, p, t0, dt) / xs
    r = wt * (cm.output(xs * xk, u0, p, t0) - y)
    cost = 0.5 * ca.sumsqr(r)
    rest = [u0, u1, t0, dt, theta, mat, off, xs, y, wt]
    # the next state dense, as the state it becomes: a structurally zero entry (a delay state fed
    # by an input alone) would leave output 0 sparser than input 0, and the compiled fold carries
    # one into the other as it stands
    value = ca.Function("greyfit_ss_value", [xk, *rest], [ca.densify(xn), cost])
    sens = sx("S", nx, nv)
    s_next = ca.mtimes(ca.jacobian(xn, xk), sens) + ca.horzcat(ca.jacobian(xn, theta), ca.SX(nx, nf))
    jrow = ca.mtimes(ca.jacobian(r, xk), sens) + ca.horzcat(ca.jacobian(r, theta), ca.SX(cm.ny, nf))
    z = ca.vertcat(xk, ca.vec(sens))
    # the symbolic sparsity of triu(JᵀJ) (e.g. no θ in an output) is the NLP's Hessian pattern
    derivs = ca.Function("greyfit_ss_sens", [z, *rest], [
        ca.densify(ca.vertcat(xn, ca.vec(s_next))), cost, ca.mtimes(jrow.T, r), ca.triu(ca.mtimes(jrow.T, jrow)),
        ca.densify(r), ca.densify(jrow)])
    return {"value": value, "sens": derivs}


# the outputs of the `sens` kernel its fold keeps per sample (r_k, J_k) instead of summing
SENS_PER_SAMPLE = (4, 5)


def kernels(oem, free: tuple[int, ...]) -> dict[str, ca.Function]:
    """`build_kernels`, built once per model structure (`kernel_key`) and shared by the solve's
    folds and the condensed Jacobian's row kernel.

    Parameters
    ----------
    oem : OutputErrorModel
        The output-error model.
    free : tuple of int
        The states whose initial value is estimated somewhere (`free_states`).

    Returns
    -------
    dict of str to casadi.Function
        As `build_kernels`.
    """
    return oem.cm.derive(("single_pass", *kernel_key(oem, free)), lambda: build_kernels(oem, free))


def build_row_kernel(oem, free: tuple[int, ...]) -> ca.Function:
    """The per-sample kernel of the condensed Jacobian: ((x_k, vec S_k), inputs as `build_kernels`)
    -> ((x_k+1, vec S_k+1), r_k, J_k), J_k = ∂r_k/∂x S_k + [∂r_k/∂θ, 0] dense (ny × (nθ + free)).

    Parameters
    ----------
    oem : OutputErrorModel
        The output-error model.
    free : tuple of int
        The states whose initial value is estimated somewhere (`free_states`).

    Returns
    -------
    casadi.Function
        An SX Function, evaluated over the samples by a compiled column loop (`Columns`).
    """
    sens = kernels(oem, free)["sens"]
    ins = [ca.SX.sym(sens.name_in(i), sens.sparsity_in(i)) for i in range(sens.n_in())]
    outs = sens(*ins)
    return ca.Function("greyfit_ss_rows", ins, [outs[0], *(outs[j] for j in SENS_PER_SAMPLE)])


def row_columns(oem):
    """The condensed Jacobian's kernel on numpy columns (`build_row_kernel`), one per model structure.

    Parameters
    ----------
    oem : OutputErrorModel
        The output-error model.

    Returns
    -------
    Columns
        Compiled where a library is (or becomes) available; see `Columns.ready`.
    """
    from greyfit.solvers.dynamics.columns import Columns

    free = free_states(oem)
    samples = sum(d.n for d in oem.data)
    key = ("single_pass_rows", *kernel_key(oem, free))
    if not oem.reused:   # a stand-in model of one request: not worth a compiler run
        return Columns(build_row_kernel(oem, free), compile=False)
    return oem.cm.derive(key, lambda: Columns(build_row_kernel(oem, free), 4 * samples))


def condensed_rows(oem, theta_s: np.ndarray, x0s: list[dict[str, float]]):
    """(J, r, output of each row) of single shooting at the measured samples, w.r.t. [θ, free x0]
    (scaled): one compiled loop per experiment carrying the sensitivities, the rows written as it
    goes (the MX graph of mapped blocks it replaces cost 6–10× the arithmetic, and every fit asks
    for this three times: at the guess, at the optimum, and in the lack-of-fit screen).

    Parameters
    ----------
    oem : OutputErrorModel
        The output-error model.
    theta_s : numpy.ndarray
        The scaled free parameters, shape (n θ,).
    x0s : list of dict
        Per experiment, state name -> initial value (physical units).

    Returns
    -------
    jac : numpy.ndarray
        Jacobian of the weighted residual, shape (measured samples × outputs, n θ + free initial states).
    res : numpy.ndarray
        The weighted residual at the measured samples, sample-major.
    groups : numpy.ndarray
        The output index of each row.
    """
    cm, layout = oem.cm, oem.layout
    nth, nx, ny = layout.size, cm.nx, cm.ny
    theta_s = np.asarray(theta_s, dtype=float).ravel()
    key = _rows_key(oem, theta_s, x0s)
    with _ROWS_LOCK:
        _ROWS_DROPS.drain()
        known = _ROWS.get(key)
    # the entry holds its model and records, so an id in a key is never reused while the entry lives
    if known is not None and known[0] is oem.cm and known[1] == _records(oem):   # the optimum's, asked again
        return tuple(a.copy() for a in known[2])
    rows = row_columns(oem)
    free = free_states(oem)
    free_at = np.asarray(free, dtype=int)
    nv = nth + free_at.size
    seed = np.hstack([np.zeros((nx, nth)), np.eye(nx)[:, free_at]]).ravel(order="F")
    parts = []
    for e, d in enumerate(oem.data):
        n = d.n
        x0 = np.array([x0s[e][s] for s in cm.states], dtype=float) / oem.xscale
        u1 = np.concatenate([d.u[:, 1:], d.u[:, -1:]], axis=1)
        dt = np.append(np.diff(d.t), 0.0)[None, :]
        _, r, j = rows(np.concatenate([x0, seed]), d.u, u1, d.t[None, :], dt, theta_s,
                       oem.layout.matrix[e], layout.offset, oem.xscale, np.where(d.mask, d.y, 0.0),
                       d.mask * oem.weights[:, None], n=n, accumulate=True)
        parts.append((r.T, j.reshape(ny, n, nv).transpose(1, 0, 2)))
    return remember_rows(oem, theta_s, x0s, assemble_rows(oem, parts))


def assemble_rows(oem, parts: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(J, r, output of each row) at the measured samples from each experiment's per-sample
    residuals and rows, as `condensed_rows` returns them.

    Parameters
    ----------
    oem : OutputErrorModel
        The output-error model (its records' masks and free initial states).
    parts : list of tuple of numpy.ndarray
        Per experiment, the weighted residual (n, ny) and the rows J_k (n, ny, nθ + free states of
        the kernels, `free_states`) at every sample.

    Returns
    -------
    tuple of numpy.ndarray
        J (measured samples × outputs, nθ + the free initial states of every experiment), r, and
        the output index of each row.
    """
    nth, ny = oem.layout.size, oem.cm.ny
    free_at = np.asarray(free_states(oem), dtype=int)
    nv = nth + free_at.size
    nw = nth + sum(len(f) for f in oem.free_x0)
    jacs, resids, groups, col = [], [], [], nth
    for e, (d, (r, per_sample)) in enumerate(zip(oem.data, parts)):
        n = d.n
        f = np.asarray(oem.free_x0[e], dtype=int)
        v = np.concatenate([np.arange(nth), nth + np.searchsorted(free_at, f)]).astype(int)
        wi = np.concatenate([np.arange(nth), col + np.arange(f.size)]).astype(int)
        col += f.size
        keep = d.mask.T.ravel()                                        # sample-major, like r
        flat = per_sample.reshape(n * ny, nv)
        if nv == nw and np.array_equal(v, np.arange(nv)) and np.array_equal(wi, v):   # the kernel's columns are J's
            jacs.append(flat[keep] if not keep.all() else np.array(flat))
        else:
            block = np.zeros((n * ny, nw))
            block[:, wi] = flat[:, v]
            jacs.append(block[keep])
        resids.append(np.ravel(r)[keep])
        groups.append(np.broadcast_to(np.arange(ny), (n, ny)).ravel()[keep])
    if len(jacs) == 1:
        return jacs[0], resids[0], groups[0]
    return np.vstack(jacs), np.concatenate(resids), np.concatenate(groups)


def remember_rows(oem, theta_s: np.ndarray, x0s: list[dict[str, float]], out: tuple) -> tuple:
    """Keep `out` (J, r, groups) as the condensed Jacobian at (θ, x0s) for the checks that ask
    again (the lack-of-fit screen); returns copies.

    Parameters
    ----------
    oem : OutputErrorModel
        The output-error model.
    theta_s : numpy.ndarray
        The scaled free parameters.
    x0s : list of dict
        Per experiment, state name -> initial value (physical units).
    out : tuple of numpy.ndarray
        (J, r, output of each row), as `condensed_rows` returns them.

    Returns
    -------
    tuple of numpy.ndarray
        Copies of `out`.
    """
    key = _rows_key(oem, np.asarray(theta_s, dtype=float).ravel(), x0s)
    with _ROWS_LOCK:
        _ROWS_DROPS.drain()
        _ROWS[key] = (oem.cm, _records(oem), out)
        while len(_ROWS) > 4:
            _ROWS.popitem(last=False)
    # forgotten with the fit's records (a long record's Jacobian is its size times the unknowns)
    weakref.finalize(oem.data[0].y, _ROWS_DROPS.drop, key)
    return tuple(a.copy() for a in out)


# the last condensed Jacobians, by everything they are computed from (the kernel, the point and a
# digest of the records, weights and parameter map): a fit's checks ask again at its optimum
_ROWS: "OrderedDict[tuple, tuple]" = OrderedDict()
_ROWS_LOCK = threading.Lock()
_ROWS_DROPS = LaterDrops(_ROWS, _ROWS_LOCK)   # entries go with their records (finalizers)


def _records(oem) -> tuple[_Same, ...]:
    return tuple(_Same(x) for d in oem.data for x in (d, d.t, d.u, d.y))


class _Same:
    """Equal when it holds the same live object: a key part that compares identities, not contents.
    It holds the object weakly, so a remembered Jacobian does not keep its fit's records alive."""

    __slots__ = ("ref", "ident")

    def __init__(self, obj: object):
        self.ref, self.ident = weakref.ref(obj), id(obj)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, _Same):
            return False
        mine = self.ref()
        return mine is not None and mine is other.ref()

    def __hash__(self) -> int:
        return self.ident


def _rows_key(oem, theta_s: np.ndarray, x0s: list[dict[str, float]]) -> tuple:
    """The records by identity, not by a digest of their contents (7 ms a digest at 200 000 samples,
    more than the pass it saves): a prepared record's arrays are read-only (`prepare_experiment`),
    and the steps of one fit share them (`prepared_once`), so the lack-of-fit screen finds the
    solve's Jacobian at the optimum."""
    x0 = tuple(tuple(sorted(x.items())) for x in x0s)
    free = tuple(map(tuple, oem.free_x0))
    small = tuple(np.ascontiguousarray(a, dtype=float).tobytes()
                  for a in (oem.weights, oem.layout.offset, oem.xscale, *oem.layout.matrix))
    o = oem.options
    # the model and the integrator settings choose the kernel (`row_columns`), which is not built to ask
    kernel = (id(oem.cm), o.integrator, o.substeps, o.input_interpolation)
    return (kernel, theta_s.tobytes(), x0, free, _records(oem), small)


# the cost at a trial point from the sensitivity pass when that pass costs at most this many times the
# simulation's instructions (3.3 for a 2-state oscillator with 2 unknowns, 13 for the 8-state seat):
# 8 simulations of 200 000 samples (63 of 340 ms) saved for at most a rejected trial point's pass
COST_BY_SENSITIVITY = 4.0


class SinglePass:
    """Cost, gradient and Gauss-Newton Hessian of single shooting at a point, from two folds."""

    def __init__(self, oem, folds: dict[str, Fold], layout: list[tuple[str, tuple[int, int]]],
                 free: tuple[int, ...]):
        """`layout`: the named blocks of the data vector (`structured._data_layout`), in order;
        `free`: the kernels' x0 directions (`free_states`)."""
        cm, nth = oem.cm, oem.layout.size
        self.nx, self.nth, self.nu, self.ny = cm.nx, nth, cm.nu, cm.ny
        self.folds = folds
        self.n = [d.n for d in oem.data]
        self.free = [np.asarray(f, dtype=int) for f in oem.free_x0]
        self.nw = nth + sum(f.size for f in self.free)
        self.offsets, k = {}, 0
        for name, (size1, size2) in layout:
            self.offsets[name] = (k, size1 * size2)
            k += size1 * size2
        free_at = np.asarray(free, dtype=int)
        nv = nth + free_at.size
        # S_0 = [0 | e_i for the free states i]
        self.seed = np.hstack([np.zeros((cm.nx, nth)), np.eye(cm.nx)[:, free_at]]).ravel(order="F")
        # [θ, x0 directions] of experiment e -> w: θ, and its free x0 entries at their columns
        self.places, col = [], nth
        for f in self.free:
            v = np.concatenate([np.arange(nth), nth + np.searchsorted(free_at, f)]).astype(int)
            self.places.append((v, np.concatenate([np.arange(nth), col + np.arange(f.size)])))
            col += f.size
        rows, cols = (np.asarray(a, dtype=int) for a in folds["sens"].fn.sparsity_out(3).get_triplet())
        pairs = []   # per experiment: (kept nonzeros of triu(J_kᵀJ_k), their (row, col) in w)
        for v, wi in self.places:
            inv = np.full(nv, -1)
            inv[v] = wi
            keep = np.nonzero((inv[rows] >= 0) & (inv[cols] >= 0))[0]
            a, b = inv[rows[keep]], inv[cols[keep]]
            pairs.append((keep, np.minimum(a, b), np.maximum(a, b)))
        pattern = np.zeros((self.nw, self.nw), dtype=bool)
        for _, a, b in pairs:
            pattern[a, b] = True
        sp_cols, sp_rows = np.nonzero(pattern.T)   # column-major order
        self.hess_sparsity = ca.Sparsity.triplet(self.nw, self.nw, sp_rows.tolist(), sp_cols.tolist())
        r_, c_ = (np.asarray(a, dtype=int) for a in self.hess_sparsity.get_triplet())
        position = np.full((self.nw, self.nw), -1)
        position[r_, c_] = np.arange(r_.size)
        # where each kept nonzero of experiment e lands among the Hessian's (one-to-one per experiment)
        self.h_maps = [(keep, position[a, b]) for keep, a, b in pairs]
        self._records: OrderedDict[float, list[dict]] = OrderedDict()
        # held weakly: a record lives as long as a solver holds it, however many solve at once
        self._attached: "weakref.WeakValueDictionary[float, np.ndarray]" = weakref.WeakValueDictionary()
        # Ipopt asks for the gradient at nearly every point whose cost it asked for (a Gauss-Newton
        # step is mostly accepted): where the sensitivity pass costs little more than the simulation,
        # the cost comes from it and the gradient and Hessian that follow are already there
        self._cost_by_sens = (folds["sens"].fn.n_instructions()
                              <= COST_BY_SENSITIVITY * folds["value"].fn.n_instructions())
        self._point: tuple[bytes, tuple[float, np.ndarray, np.ndarray]] | None = None
        self._rows: tuple[bytes, list[tuple[np.ndarray, np.ndarray]]] | None = None
        self._lock = threading.RLock()   # the bound folds' buffers are rewritten per call
        self._forgotten: deque[float] = deque()   # tokens whose models are gone (`forget`)

    def attach(self, record: np.ndarray) -> None:
        """Give the callbacks a record: the data vector (`structured._data_layout`) with its token
        last. The NLP passes only the token; the record is bound to the folds at its first use. It
        is held weakly: the caller keeps it alive while it solves.

        Parameters
        ----------
        record : numpy.ndarray
            The data vector and the token.
        """
        with self._lock:
            self._drop_forgotten()
            self._attached[float(record[-1])] = record

    def forget(self, token: float) -> None:
        """Drop what is bound to `token` (its record's copies, the folds' buffers, its last point).

        The model that owns the token calls it when it goes (`structured._token_record`): a record
        bound here is 150 MB at 10⁶ samples, and keeping the last two, as this did, made a process
        that fits one long record after another peak higher at each.

        Parameters
        ----------
        token : float
            The token of a model's record.
        """
        # called from a finalizer, maybe inside this pass's own locked work: queued, never waited on
        # (see `later_drops`); the next attach or evaluation drops it, before it binds a new record
        self._forgotten.append(token)

    def _drop_forgotten(self) -> None:
        """Drop the queued tokens' records and points (the caller holds the lock)."""
        while self._forgotten:
            try:
                token = self._forgotten.popleft()
            except IndexError:
                return
            tail = np.float64(token).tobytes()   # a point's key ends with its record's token
            self._records.pop(token, None)
            if self._point is not None and self._point[0].endswith(tail):
                self._point = None
            if self._rows is not None and self._rows[0].endswith(tail):
                self._rows = None

    def _record(self, p: np.ndarray) -> list[dict]:
        """The record whose token `p` ends with, bound to the two folds (once per token)."""
        self._drop_forgotten()
        token = float(p[-1])
        known = self._records.get(token)
        if known is not None:
            self._records.move_to_end(token)
            return known
        attached = self._attached.get(token)
        if attached is None:
            raise RuntimeError("single shooting: no record attached for this solve")
        p = attached

        def block(name: str) -> np.ndarray:
            start, size = self.offsets[name]
            return np.array(p[start:start + size], dtype=float)

        out = []
        for e, n in enumerate(self.n):
            u, t = block(f"U{e}"), block(f"T{e}")
            rest = [u, np.concatenate([u[self.nu:], u[-self.nu:]]), t, np.append(np.diff(t), 0.0),
                    np.zeros(self.nth), block(f"M{e}"), block("off"), block("xs"), block(f"Y{e}"), block(f"W{e}")]
            value = self.folds["value"].bind([np.zeros(self.nx), *rest], n)
            sens = self.folds["sens"].bind([np.zeros(self.nx + self.seed.size), *rest], n)
            sens.args[0][self.nx:] = self.seed
            out.append({"x0": block(f"X0{e}"), "value": value, "sens": sens})
        self._records[token] = out
        # a record per live solver of this structure; one fit's solves share one (a long record
        # held for solvers already gone would cost its size again)
        while len(self._records) > 2:
            self._records.popitem(last=False)
        return out

    def _x0(self, e: int, rec: dict, w: np.ndarray, state: np.ndarray) -> None:
        """Write the scaled x0 of experiment e at w into the first nx entries of `state`."""
        state[:self.nx] = rec["x0"]   # the data block is 0 where x0 is free
        state[self.free[e]] += w[self.places[e][1][self.nth:]]

    def cost(self, w: np.ndarray, p: np.ndarray) -> float:
        """½‖r‖² at w by the simulation alone.

        Parameters
        ----------
        w : numpy.ndarray
            The decision vector [θ, free x0] (scaled).
        p : numpy.ndarray
            Ends with the token of an attached record (`attach`).

        Returns
        -------
        float
            The cost.
        """
        if self._cost_by_sens:
            return self.derivatives(w, p)[0]
        total = 0.0
        with self._lock:
            for e, rec in enumerate(self._record(p)):
                bound = rec["value"]
                self._x0(e, rec, w, bound.args[0])
                bound.args[5][:] = w[:self.nth]
                total += float(bound(copy=False)[1][0])
        return total

    def derivatives(self, w: np.ndarray, p: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        """(½‖r‖², Jᵀr, nonzeros of triu(JᵀJ) in `hess_sparsity`) at w, one sensitivity pass
        per point (the last point's result is kept).

        Parameters
        ----------
        w : numpy.ndarray
            The decision vector [θ, free x0] (scaled).
        p : numpy.ndarray
            Ends with the token of an attached record (`attach`).

        Returns
        -------
        tuple of (float, numpy.ndarray, numpy.ndarray)
            The cost, the gradient (shape (n w,)) and the Hessian's nonzeros.
        """
        key = w.tobytes() + p[-1:].tobytes()
        with self._lock:
            point = self._point
            if point is not None and point[0] == key:
                return point[1]
            total, grad, hess = 0.0, np.zeros(self.nw), np.zeros(self.hess_sparsity.nnz())
            parts = []
            for e, rec in enumerate(self._record(p)):
                bound = rec["sens"]
                self._x0(e, rec, w, bound.args[0])
                bound.args[5][:] = w[:self.nth]
                # the fold's own buffers, valid until its next call: the sums are read here, and the
                # rows are kept as views (a copy per pass, 1 MB at 40 000 samples, was most of the
                # pass's memory traffic): the record's next pass rewrites them and, under the same
                # lock, replaces `_rows`, whose key then names its point; `rows_at` gives them once
                # to `assemble_rows`, which copies what it keeps (one token is one fit's record)
                _, c, g, h, r, j = bound(copy=False)
                total += float(c[0])
                v, wi = self.places[e]
                grad[wi] += g[v]
                keep, at = self.h_maps[e]
                hess[at] += h[keep]
                n = self.n[e]
                # per sample: r_k (ny), J_k (ny × nv) column-major
                parts.append((r.reshape(n, self.ny), j.reshape(n, -1, self.ny).transpose(0, 2, 1)))
            result = (total, grad, hess)
            self._point = (key, result)
            self._rows = (key, parts)
        return result

    def rows_at(self, w: np.ndarray, token: float) -> list[tuple[np.ndarray, np.ndarray]] | None:
        """Per experiment, the residual (n, ny) and the rows J_k (n, ny, nθ + free states) of the
        last sensitivity pass, if it ran at w for the record of `token` (the solve's last accepted
        point is its optimum: the fit's checks read J there without another pass). They are given
        once; the pass keeps them no longer.

        Parameters
        ----------
        w : numpy.ndarray
            The decision vector [θ, free x0] (scaled).
        token : float
            The record's token (`attach`).

        Returns
        -------
        list of tuple of numpy.ndarray or None
            None when the last pass ran elsewhere.
        """
        key = np.asarray(w, dtype=float).tobytes() + np.array([token], dtype=float).tobytes()
        with self._lock:
            if self._rows is None or self._rows[0] != key:
                return None
            parts = self._rows[1]
            # taken once: a structure's pass would otherwise hold a long record's rows (n × outputs
            # × unknowns) until its next fit
            self._rows = None
            return parts


class _PassCallback(ca.Callback):
    """One output set of `SinglePass` as a CasADi Function of (w, p), over CasADi's own buffers."""

    def __init__(self, name: str, single_pass: SinglePass, what: str):
        ca.Callback.__init__(self)
        self.single_pass, self.what = single_pass, what
        sp = single_pass
        self.outs = {"cost": [ca.Sparsity.dense(1, 1)],
                     "grad": [ca.Sparsity.dense(1, 1), ca.Sparsity.dense(sp.nw, 1)],
                     "hess": [sp.hess_sparsity]}[what]
        # CasADi may build (never evaluate) derivatives of an NLP's functions
        self.construct(name, {"enable_fd": True})

    def get_n_in(self) -> int:
        return 2

    def get_n_out(self) -> int:
        return len(self.outs)

    def get_sparsity_in(self, i: int) -> ca.Sparsity:
        return ca.Sparsity.dense(self.single_pass.nw if i == 0 else 1, 1)   # w, the record's token

    def get_sparsity_out(self, i: int) -> ca.Sparsity:
        return self.outs[i]

    def has_eval_buffer(self) -> bool:
        return True

    def eval_buffer(self, arg, res) -> int:
        w = np.frombuffer(arg[0], dtype=float).copy()
        p = np.frombuffer(arg[1], dtype=float)
        outs = [np.frombuffer(r, dtype=float) if r is not None else np.zeros(0) for r in res]
        if self.what == "cost":
            values = [np.array([self.single_pass.cost(w, p)])]
        else:
            f, grad, hess = self.single_pass.derivatives(w, p)
            values = [np.array([f]), grad] if self.what == "grad" else [hess]
        for out, value in zip(outs, values):
            if out.size:   # an output nobody asked for has no buffer
                out[:] = value
        return 0


def callbacks(single_pass: SinglePass) -> dict[str, ca.Callback]:
    """The cost, gradient (with the cost) and Hessian callbacks of `single_pass`.

    Parameters
    ----------
    single_pass : SinglePass
        The evaluator the callbacks share (and its point cache).

    Returns
    -------
    dict of str to casadi.Callback
        ``"cost"`` (w, p) -> f; ``"grad"`` (w, p) -> (f, ∇f); ``"hess"`` (w, p) -> triu(JᵀJ).
        The caller keeps them alive as long as any Function built on them.
    """
    return {what: _PassCallback(f"greyfit_ss_{what}", single_pass, what) for what in ("cost", "grad", "hess")}
