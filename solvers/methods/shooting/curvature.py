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

import casadi as ca
import numpy as np


class GapCurvature:
    """Collects the gap blocks in the order `build_multiple_shooting` appends them to g."""

    def __init__(self, oem, map_mode: str = "serial"):
        self.oem, self.map_mode = oem, map_mode
        self.blocks: list[tuple] = []
        self.n_gap = 0
        self._functions: dict[tuple[int, int], tuple[ca.Function, np.ndarray]] = {}

    def add(self, e: int, node_column: int, ks: np.ndarray, length: int, cols: np.ndarray) -> None:
        """Gaps of experiment e for intervals starting at nodes `ks` (each `length` samples,
        starting at sample `cols[j*length]`); node k's scaled states sit at w[node_column + nx k].

        Parameters
        ----------
        e : int
            Index of the experiment.
        node_column : int
            Index in the decision vector w of the experiment's first node.
        ks : numpy.ndarray
            Indices of the nodes that start the intervals.
        length : int
            Samples per interval.
        cols : numpy.ndarray
            The samples the intervals step from, `length` per interval, interval by interval.

        Returns
        -------
        None
            The block is appended to `blocks`; `n_gap` grows by nx × len(ks).
        """
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
        """The NLP's variables and parameter constraints g_par(θ), which follow the gaps in g.

        Parameters
        ----------
        w : casadi.MX
            The NLP's decision vector [θ, nodes] (scaled).
        theta : casadi.MX
            The symbol of the scaled free parameters (w's first entries).
        g_par : list of casadi.MX
            The parameter constraints, appended to g after the gaps.

        Returns
        -------
        GapCurvature
            Itself, now callable as lam_g -> Σ λᵀ∇²g.
        """
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
        """Σ_gaps λᵀ∇²g as an (n_w × n_w) MX; λ is the first `n_gap` entries of lam_g.

        Parameters
        ----------
        w : casadi.MX
            The NLP's decision vector [θ, nodes] (scaled), n_w entries.
        lam_g : casadi.MX
            The constraints' multipliers; the gaps' come first.

        Returns
        -------
        casadi.MX
            The gaps' curvature, shape (n_w, n_w): θθ blocks summed over the intervals, node blocks
            scattered into place.
        """
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
