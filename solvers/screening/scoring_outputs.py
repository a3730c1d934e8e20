"""Output-error scoring: trace the residual of the *outputs* to a term in any state equation.

A candidate term g(t) added with a new parameter β to the equations of some states (measured or
not) changes the outputs, to first order, by the output sensitivity ∂y/∂β along the fitted
trajectory: S_{k+1} = A_k S_k + D0_k g_k + D1_k g_{k+1}, ∂y_k/∂β = H_k S_k, where A is the step's
Jacobian in the state and D0/D1 its Jacobians in a disturbance added to the right-hand side (held
or linear between samples like the inputs). The unmeasured states come from the model. Effects in
the output path (offset, gain, a sign-blind sensor, clipping) enter the outputs directly.

Regressing the weighted output residual on ∂y/∂β with the sensitivities of the existing parameters
and free initial states projected out is one Gauss-Newton step of the augmented output-error fit:
the score (Lagrange-multiplier) test of β = 0. A parameter that may vary in time is scored the same
way with g = ∂f/∂θ · shape(t); forward selection over switch times is the discrete form of asking
where the cost's gradient with respect to θ(t) wants a change.
"""
from __future__ import annotations

from types import SimpleNamespace
from typing import cast

import casadi as ca
import numpy as np

from greyfit.solvers.dynamics.columns import Columns
from greyfit.solvers.dynamics.integration import make_step
from greyfit.solvers.methods.shooting import OutputErrorModel, sensitivity_jacobian
from greyfit.solvers.model.compiler import CompiledModel
from greyfit.solvers.screening.scoring import RegressionScorer


def _disturbed_step(oem: OutputErrorModel) -> Columns:
    """(x, u0, u1, p, t0, dt) -> ∂x+/∂x, ∂x+/∂d0, ∂x+/∂d1 at d = 0, for a disturbance d added to ẋ
    (held or linear between samples like the inputs), on numpy columns.

    Built once per compiled model and integrator settings (every output-error fit screens for lack
    of fit, and building the step and its Jacobians costs more than the screen's arithmetic); an SX
    step (RK4) is differentiated in SX, so the per-sample Jacobians run as one compiled loop.
    """
    cm, o = oem.cm, oem.options
    key = ("disturbed_sens", o.integrator, o.substeps, o.input_interpolation)
    samples = sum(d.n for d in oem.data)
    if not isinstance(cm, CompiledModel):   # a stand-in model: for this request only, not compiled
        return Columns(_disturbed_sens(cm, o), compile=False)
    return cm.derive(key, lambda: Columns(_disturbed_sens(cm, o), 2 * samples))


def _disturbed_sens(cm: CompiledModel, options) -> ca.Function:
    x, u, d = ca.SX.sym("x", cm.nx), ca.SX.sym("u", cm.nu), ca.SX.sym("d", cm.nx)
    p, t = ca.SX.sym("p", cm.np), ca.SX.sym("t")
    ud = ca.vertcat(u, d)
    rhs = ca.Function("rhs_d", [x, ud, p, t], [cm.rhs(x, u, p, t) + d])
    disturbed = SimpleNamespace(rhs=rhs, nx=cm.nx, nu=cm.nu + cm.nx, np=cm.np, model=cm.model)
    # the step builder reads only rhs, nx, nu, np and model: a namespace with the disturbed rhs
    step = make_step(cast(CompiledModel, disturbed), options)
    sym = ca.SX.sym if step.is_a("SXFunction") else ca.MX.sym   # CVODES is MX only
    xm, u0m, u1m = sym("x", cm.nx), sym("u0", cm.nu), sym("u1", cm.nu)
    d0m, d1m = sym("d0", cm.nx), sym("d1", cm.nx)
    pm, t0m, dtm = sym("p", cm.np), sym("t0"), sym("dt")
    xn = step(xm, ca.vertcat(u0m, d0m), ca.vertcat(u1m, d1m), pm, t0m, dtm)
    # differentiated in d alone (the inputs' columns were 13 % of the seat's kernel, never read),
    # at d = 0; dense: a Jacobian may be structurally zero (d1 under zero-order hold), and the
    # callers reshape
    jac = [ca.jacobian(xn, v) for v in (xm, d0m, d1m)]
    zero = ca.DM.zeros(2 * cm.nx)
    jac = [ca.densify(ca.substitute(j, ca.vertcat(d0m, d1m), zero)) for j in jac]
    return ca.Function("greyfit_disturbed_sens", [xm, u0m, u1m, pm, t0m, dtm], jac)


class OutputScorer(RegressionScorer):
    """Regression of the weighted output residual on candidate output sensitivities."""

    def __init__(self, oem: OutputErrorModel, theta_s: np.ndarray, x0s: list[dict[str, float]]):
        self.oem = oem
        cm = oem.cm
        jac, r, self.groups = sensitivity_jacobian(oem, theta_s, x0s)
        self.states, self.a, self.d0, self.d1, self.hx, self.y = [], [], [], [], [], []
        sens = _disturbed_step(oem)
        for e, d in enumerate(oem.data):
            p = np.asarray(oem.layout.full(e, theta_s), dtype=float).ravel()
            x0 = np.array([x0s[e][s] for s in cm.states])
            states = oem.numeric_states(e, x0, p)
            n = d.n
            u0, u1, t0, dt = oem.step_inputs(d, 0, n - 1)
            a, j0, j1 = sens(states[:, :-1], u0, u1, p, t0, dt, n=n - 1)
            self.a.append(np.array(a).reshape(cm.nx, n - 1, cm.nx).transpose(1, 0, 2))
            self.d0.append(np.array(j0).reshape(cm.nx, n - 1, cm.nx).transpose(1, 0, 2))
            self.d1.append(np.array(j1).reshape(cm.nx, n - 1, cm.nx).transpose(1, 0, 2))
            y, hx, _ = oem.output_jacobians(e, states, p)
            self.hx.append(hx)
            self.y.append(y)
            self.states.append(states)
        ok = np.isfinite(r) & np.all(np.isfinite(jac), axis=1)
        self.ok = ok
        # the rows interleave the outputs sample by sample: each output is a series of its own
        kept = np.asarray(self.groups)[ok]
        labels = np.unique(kept)
        self.series = [np.flatnonzero(kept == g) for g in labels] if labels.size > 1 else None
        # measured − model, as the equation residual: β > 0 then means "add +β·g to the model"
        super().__init__(-r[ok], jac[ok])

    def parameter_moves(self, delta: np.ndarray) -> dict[str, float]:
        """Physical changes of the shared free parameters from a step in the scorer's columns
        (scaled θ, then free initial states).

        Parameters
        ----------
        delta : numpy.ndarray
            Step in the Jacobian's columns: scaled θ first, then the free initial states (ignored).

        Returns
        -------
        dict of str to float
            Label -> physical change, for the parameters shared by all experiments.
        """
        layout = self.oem.layout
        return {label: float(delta[i] * layout.scale[i]) for i, label in enumerate(layout.labels)
                if layout.experiment[i] is None}

    def trajectories(self):
        """(states, inputs, times, experiment name) of the fitted simulation, per experiment.

        Returns
        -------
        list of tuple
            Per experiment: simulated states (nx, n), inputs (nu, n), times (n,), the experiment's name.
        """
        return [(x, d.u, d.t, d.name) for x, d in zip(self.states, self.oem.data)]

    def stack(self, regressor: dict[int, list[np.ndarray]] | None,
              outputs: dict[int, list[np.ndarray]] | None = None) -> np.ndarray | None:
        """Output sensitivity column(s) of a term: forcing on equations and/or direct on outputs.

        Parameters
        ----------
        regressor : dict of int to list of numpy.ndarray or None
            Equation index -> per-experiment forcing column(s), (n,) or (n, m).
        outputs : dict of int to list of numpy.ndarray or None
            Output index -> per-experiment direct column(s) on that output.

        Returns
        -------
        numpy.ndarray or None
            Weighted ∂y/∂β at the measured samples, (rows,) or (rows, m); None when both are empty.
        """
        return self.stack_many([(regressor, outputs)])[0]

    def stack_many(self, items: list[tuple[dict | None, dict | None]]) -> list[np.ndarray | None]:
        """`stack` for many candidates with one propagation (the loop over samples is the cost).

        Parameters
        ----------
        items : list of tuple of (dict or None, dict or None)
            (regressor, outputs) of each candidate, as `stack` takes them.

        Returns
        -------
        list of numpy.ndarray or None
            One entry per item, as `stack` returns it: views of the matrix `stack_matrix` makes.
        """
        return column_views(*self.stack_matrix(items))

    def stack_matrix(self, items: list[tuple[dict | None, dict | None]]) \
            -> tuple[np.ndarray, np.ndarray, np.ndarray, list[bool]]:
        """The columns of `stack_many` side by side, as one C-ordered matrix.

        Parameters
        ----------
        items : list of tuple of (dict or None, dict or None)
            (regressor, outputs) of each candidate, as `stack` takes them.

        Returns
        -------
        matrix : numpy.ndarray
            Weighted ∂y/∂β at the measured samples, rows × all the items' columns.
        starts, ends : numpy.ndarray
            Item k's columns are ``matrix[:, starts[k]:ends[k]]`` (none when they are equal).
        vectors : list of bool
            Whether item k is one column given as a vector (`stack` returns it 1-D).
        """
        oem, cm = self.oem, self.oem.cm
        widths, vectors = [], []
        for regressor, outputs in items:
            merged = {**(regressor or {}), **(outputs or {})}
            if not merged:
                widths.append(0)
                vectors.append(True)
                continue
            sample = next(iter(merged.values()))[0]
            widths.append(1 if np.ndim(sample) == 1 else sample.shape[1])
            vectors.append(np.ndim(sample) == 1)
        # the items that force equations take the first columns: their propagated sensitivities are
        # then added to a slice of the result, not scattered into it
        order = sorted(range(len(items)), key=lambda k: not items[k][0])
        starts = np.zeros(len(items), dtype=int)
        starts[order] = np.concatenate([[0], np.cumsum([widths[k] for k in order])[:-1]])
        ends = starts + np.array(widths, dtype=int)
        total = int(sum(widths))
        if total == 0:
            return np.zeros((self.r.size, 0)), starts, ends, vectors
        blocks = []
        for e, d in enumerate(oem.data):
            n = d.n
            jy = np.zeros((n, cm.ny, total))
            forcing: dict[int, list[tuple[int, np.ndarray]]] = {}   # column -> (equation, values)
            for (regressor, outputs), lo, hi in zip(items, starts, ends):
                for i, cols in (regressor or {}).items():
                    block = np.reshape(cols[e], (n, hi - lo))
                    for c in range(hi - lo):
                        if np.any(block[:, c]):   # a zero column (or part) adds nothing to propagate
                            forcing.setdefault(lo + c, []).append((i, block[:, c]))
                for j, cols in (outputs or {}).items():
                    jy[:, j, lo:hi] += np.reshape(cols[e], (n, hi - lo))
            if forcing and n >= BY_EQUATION_FROM and all(len(parts) == 1 for parts in forcing.values()):
                # every column forces one equation (what the effect catalogue's terms do)
                ordered = sorted(forcing)
                columns = [forcing[c][0] for c in ordered]
                if ordered[-1] == len(ordered) - 1:   # columns 0 .. k − 1: every forcing column is nonzero
                    propagate_by_equation(self.a[e], self.d0[e], self.d1[e], self.hx[e], columns,
                                          into=jy[:, :, :len(ordered)])
                else:
                    jy[:, :, ordered] += propagate_by_equation(self.a[e], self.d0[e], self.d1[e], self.hx[e], columns)
            elif forcing:
                active = np.array(sorted(forcing), dtype=int)
                # written straight in the recursion's layout (sample, column, equation)
                laid = np.zeros((n, _padded(active.size), cm.nx))
                for slot, c in enumerate(active):
                    for i, values in forcing[c]:
                        laid[:, slot, i] = values
                jy[:, :, active] += _propagate_laid(self.a[e], self.d0[e], self.d1[e], self.hx[e], laid, active.size)
            jy *= oem.weights[None, :, None]
            # rows (sample, output) where measured; a complete record needs no gather
            blocks.append(jy.reshape(n * cm.ny, total) if d.mask.all() else jy[d.mask.T])
        g = blocks[0] if len(blocks) == 1 else np.concatenate(blocks)
        if not self.ok.all():
            g = g[self.ok]
        return g, starts, ends, vectors


def column_views(matrix: np.ndarray, starts: np.ndarray, ends: np.ndarray,
                 vectors: list[bool]) -> list[np.ndarray | None]:
    """Each item's columns of `OutputScorer.stack_matrix`'s matrix, as `OutputScorer.stack` gives them.

    Parameters
    ----------
    matrix, starts, ends, vectors
        As `OutputScorer.stack_matrix` returns them.

    Returns
    -------
    list of numpy.ndarray or None
        Per item: a view of its column (1-D) or columns, None when it has none.
    """
    return [None if hi == lo else (matrix[:, lo] if vec else matrix[:, lo:hi])
            for lo, hi, vec in zip(starts.tolist(), ends.tolist(), vectors)]


def propagate(a: np.ndarray, d0: np.ndarray, d1: np.ndarray, hx: np.ndarray, forcing: np.ndarray) -> np.ndarray:
    """Output sensitivities (n, ny, w) of w forcing columns (n, nx, w), from S_0 = 0:
    S_{k+1} = A_k S_k + D0_k f_k + D1_k f_{k+1}, ∂y_k = H_k S_k.

    The forcing terms and the outputs are evaluated for all samples at once; only the recursion in
    A_k is a loop, one small product per sample (the loop, not the arithmetic, is the cost).

    Parameters
    ----------
    a : numpy.ndarray
        (n − 1, nx, nx) step Jacobians A_k in the state.
    d0, d1 : numpy.ndarray
        (n − 1, nx, nx) step Jacobians in the disturbance at the start and end of each interval.
    hx : numpy.ndarray
        (n, ny, nx) output Jacobians H_k.
    forcing : numpy.ndarray
        (n, nx, w) forcing columns on the state equations.

    Returns
    -------
    numpy.ndarray
        (n, ny, w) output sensitivities.
    """
    n, nx, w = forcing.shape
    if n > 1 and _recursion(nx, hx.shape[1], w).ready():
        laid = np.zeros((n, _padded(w), nx))
        laid[:, :w, :] = forcing.transpose(0, 2, 1)
        return _propagate_laid(a, d0, d1, hx, laid, w)
    return _propagate_numpy(a, d0, d1, hx, forcing)


def _propagate_numpy(a: np.ndarray, d0: np.ndarray, d1: np.ndarray, hx: np.ndarray,
                     forcing: np.ndarray) -> np.ndarray:
    """`propagate` by numpy's batched products and a Python loop over the samples."""
    n = forcing.shape[0]
    drive = np.matmul(d0, forcing[:-1]) + np.matmul(d1, forcing[1:])
    sens = np.empty((n,) + forcing.shape[1:])
    sens[0] = 0.0
    s = sens[0]
    for k in range(n - 1):
        s = a[k] @ s
        s += drive[k]
        sens[k + 1] = s
    return np.matmul(hx, sens)


def _propagate_laid(a: np.ndarray, d0: np.ndarray, d1: np.ndarray, hx: np.ndarray, laid: np.ndarray,
                    w: int) -> np.ndarray:
    """`propagate` of the first w of the forcing columns `laid` (n, width, nx), width a multiple of
    `PROPAGATE_COLUMNS` and the rest zero: one compiled loop where its library is ready (numpy's
    batched products of 8 × 8 blocks and a Python loop cost 17 ms of a lack-of-fit screen on a
    1 000-sample, 8-state model), else the numpy recursion."""
    n, width, nx = laid.shape
    ny = hx.shape[1]
    loop = _recursion(nx, ny, w)
    if not (n > 1 and loop.ready()):
        return propagate(a, d0, d1, hx, laid[:, :w, :].transpose(0, 2, 1))
    f = laid.reshape(n, nx * width).T                     # column k: vec of f_k (nx × width)
    blocks = [m.transpose(0, 2, 1).reshape(m.shape[0], -1).T for m in (a, d0, d1)]
    h = hx[1:].transpose(0, 2, 1).reshape(n - 1, ny * nx).T
    _, y = loop(np.zeros(nx * width), *blocks, f[:, :-1], f[:, 1:], h, n=n - 1, accumulate=True)
    out = np.zeros((n, ny, w))
    out[1:] = y.T.reshape(n - 1, width, ny).transpose(0, 2, 1)[:, :, :w]
    return out


def propagate_by_equation(a: np.ndarray, d0: np.ndarray, d1: np.ndarray, hx: np.ndarray,
                          columns: list[tuple[int, np.ndarray]], into: np.ndarray | None = None) -> np.ndarray:
    """`propagate` of forcing columns that each force one state equation: column c adds values_c to
    equation i_c, so its drive is D0_k[:, i_c] f_k + D1_k[:, i_c] f_k+1, not two dense products.

    On the seat model (8 states, 28 candidate columns) the dense drive and the output products were
    three quarters of the recursion's arithmetic. The columns go to the compiled loop in groups of
    `PROPAGATE_COLUMNS` that share an equation, and where the outputs are a constant selection of
    the states (H_k a 0/1 row picker, as `y = x_i` makes it) the loop returns S_k and the rows are
    picked here; elsewhere it also forms H_k S_k.

    Parameters
    ----------
    a, d0, d1 : numpy.ndarray
        (n − 1, nx, nx) step Jacobians, as `propagate` takes them.
    hx : numpy.ndarray
        (n, ny, nx) output Jacobians.
    columns : list of tuple of (int, numpy.ndarray)
        Per column: the equation it forces and its values at the n samples.
    into : numpy.ndarray or None, optional
        (n, ny, len(columns)) array (a view, say) the sensitivities are added to.

    Returns
    -------
    numpy.ndarray
        (n, ny, len(columns)) output sensitivities, as `propagate` returns them (`into` plus them,
        where given).
    """
    if into is None:
        into = np.zeros((hx.shape[0], hx.shape[1], len(columns)))
    n, ny, nx = hx.shape
    by_equation: dict[int, list[int]] = {}
    for c, (i, _) in enumerate(columns):
        by_equation.setdefault(i, []).append(c)
    group_equation: list[int] = []
    slot = np.empty(len(columns), dtype=int)
    for i, members in sorted(by_equation.items()):
        for lo in range(0, len(members), PROPAGATE_COLUMNS):
            for j, c in enumerate(members[lo:lo + PROPAGATE_COLUMNS]):
                slot[c] = len(group_equation) * PROPAGATE_COLUMNS + j
            group_equation.append(i)
    picked = _picked_rows(hx)
    loop = _recursion_by_equation(nx, 0 if picked is not None else ny, len(group_equation))
    if not (n > 1 and loop.ready()):
        forcing = np.zeros((n, nx, len(columns)))
        for c, (i, values) in enumerate(columns):
            forcing[:, i, c] = values
        # numpy until the grouped loop is built (`propagate` would start building the dense one too)
        into += _propagate_numpy(a, d0, d1, hx, forcing)
        return into
    width = len(group_equation) * PROPAGATE_COLUMNS
    f = np.zeros((width, n), order="F")   # F order: the per-sample slices below need no copy
    for c, (_, values) in enumerate(columns):
        f[slot[c]] = values
    eq = np.array(group_equation)
    per_sample = [a.transpose(0, 2, 1).reshape(n - 1, nx * nx).T,
                  d0[:, :, eq].transpose(0, 2, 1).reshape(n - 1, eq.size * nx).T,
                  d1[:, :, eq].transpose(0, 2, 1).reshape(n - 1, eq.size * nx).T, f[:, :-1], f[:, 1:]]
    if picked is None:
        per_sample.append(hx[1:].transpose(0, 2, 1).reshape(n - 1, ny * nx).T)
    outs = loop(np.zeros(nx * width), *per_sample, n=n - 1, accumulate=True)
    # per sample, the loop's outputs are (rows × width) column-major: as (n − 1, width, rows) a view;
    # the columns are gathered first, over the contiguous rows (a gather on the last axis of 2 MB
    # took longer than the loop)
    rows = outs[0].T.reshape(n - 1, width, nx) if picked is not None else outs[1].T.reshape(n - 1, width, ny)
    y = rows[:, slot, :].transpose(0, 2, 1)
    into[1:] += y if picked is None or np.array_equal(picked, np.arange(nx)) else y[:, picked, :]
    return into


def _picked_rows(hx: np.ndarray) -> np.ndarray | None:
    """The state each output reads where every H_k is the same 0/1 row picker, else None."""
    h = hx[0]
    if not (np.all((h == 0) | (h == 1)) and np.all(h.sum(axis=1) == 1) and np.all(hx == h)):
        return None
    return np.argmax(h, axis=1)


def _recursion_by_equation(nx: int, ny: int, groups: int) -> Columns:
    """(S_k, A_k, D0_k[:, eq], D1_k[:, eq], f_k, f_k+1[, H_k+1]) -> (S_k+1[, H_k+1 S_k+1]) for `groups`
    groups of `PROPAGATE_COLUMNS` columns, group g forcing equation eq_g; ny = 0: no output product
    (the caller picks rows of S). Compiled in the background on first use."""
    key = (nx, ny, groups, "by equation")
    if key not in _RECURSIONS:
        sx, w = ca.SX.sym, PROPAGATE_COLUMNS
        s, a = sx("s", nx * groups * w), sx("a", nx, nx)
        c0, c1, f0, f1 = sx("c0", nx, groups), sx("c1", nx, groups), sx("f0", groups * w), sx("f1", groups * w)
        drive = ca.horzcat(*[ca.mtimes(c0[:, g], f0[g * w:(g + 1) * w].T) + ca.mtimes(c1[:, g], f1[g * w:(g + 1) * w].T)
                             for g in range(groups)])
        step = ca.mtimes(a, ca.reshape(s, nx, groups * w)) + drive
        inputs, outputs = [s, a, c0, c1, f0, f1], [ca.vec(step)]
        if ny:
            h = sx("h", ny, nx)
            inputs.append(h)
            outputs.append(ca.mtimes(h, step))
        fn = ca.Function(f"greyfit_propagate_eq_{nx}_{ny}_{groups}", inputs, outputs)
        if len(_RECURSIONS) >= 64:
            _RECURSIONS.clear()
        _RECURSIONS[key] = Columns(fn)
    return _RECURSIONS[key]


# records shorter than this take the dense recursion: there the arithmetic the grouping saves is less
# than the Python around it (101 samples: 0.1 ms slower grouped)
BY_EQUATION_FROM = 256

# the compiled recursion takes the columns in groups of this many (zero-padded): a few libraries per
# model size serve every screen, whatever the number of candidates
PROPAGATE_COLUMNS = 8


def _padded(w: int) -> int:
    return -(-w // PROPAGATE_COLUMNS) * PROPAGATE_COLUMNS
_RECURSIONS: dict[tuple, Columns] = {}


def _recursion(nx: int, ny: int, w: int) -> Columns:
    """(S_k, A_k, D0_k, D1_k, f_k, f_k+1, H_k+1) -> (S_k+1, H_k+1 S_k+1), S_k+1 = A_k S_k + D0_k f_k +
    D1_k f_k+1, on numpy columns, for nx states, ny outputs and w forcing columns (padded to a
    multiple of `PROPAGATE_COLUMNS`); compiled in the background on first use."""
    width = _padded(w)
    key = (nx, ny, width)
    if key not in _RECURSIONS:
        sx = ca.SX.sym
        s, a, d0, d1 = sx("s", nx * width), sx("a", nx, nx), sx("d0", nx, nx), sx("d1", nx, nx)
        f0, f1, h = sx("f0", nx, width), sx("f1", nx, width), sx("h", ny, nx)
        step = ca.mtimes(a, ca.reshape(s, nx, width)) + ca.mtimes(d0, f0) + ca.mtimes(d1, f1)
        fn = ca.Function(f"greyfit_propagate_{nx}_{ny}_{width}", [s, a, d0, d1, f0, f1, h],
                         [ca.vec(step), ca.mtimes(h, step)])
        if len(_RECURSIONS) >= 64:
            _RECURSIONS.clear()
        _RECURSIONS[key] = Columns(fn)
    return _RECURSIONS[key]
