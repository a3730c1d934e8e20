"""Multiple shooting: nodes as decision variables started from the data, the gaps as equality constraints."""
from __future__ import annotations

import casadi as ca
import numpy as np

from greyfit.solvers.methods.node_initialisation import node_states
from greyfit.solvers.methods.shooting import structured as shooting_structured
from greyfit.solvers.methods.shooting.curvature import GapCurvature
from greyfit.solvers.methods.shooting.model import MAP_MODE, OutputErrorModel
from greyfit.solvers.nlp.problem import (
    LeastSquaresProblem,
    parameter_constraints,
    theta_bounds,
)


def _node_indices(n: int, interval: int) -> np.ndarray:
    idx = list(range(0, n - 1, interval)) + [n - 1]
    return np.array(idx)


def _node_guess(oem: OutputErrorModel, node_sets: list[np.ndarray]):
    """w0 of multiple shooting: nodes from the data where a state is measured, else from a
    simulation at this start (solvers/methods/node_initialisation.py)."""
    def initial_guess(theta_phys: np.ndarray) -> np.ndarray:
        parts = [theta_phys / oem.layout.scale]
        for e, states in enumerate(node_states(oem, theta_phys)):
            parts.append((states[:, node_sets[e]] / oem.xscale[:, None]).ravel(order="F"))
        return np.concatenate(parts)
    return initial_guess


def _node_bounds(oem: OutputErrorModel, node_sets: list[np.ndarray]) -> tuple[list, list]:
    """Node bounds (scaled): the known initial states are fixed, the rest free."""
    lbw_x, ubw_x = [], []
    for d, nodes in zip(oem.data, node_sets):
        lo = np.full((oem.cm.nx, nodes.size), -np.inf)
        hi = np.full((oem.cm.nx, nodes.size), np.inf)
        for i, v in d.x0_known.items():
            lo[i, 0] = hi[i, 0] = v / oem.xscale[i]
        lbw_x.append(lo.ravel(order="F"))
        ubw_x.append(hi.ravel(order="F"))
    return lbw_x, ubw_x


def build_multiple_shooting(oem: OutputErrorModel) -> LeastSquaresProblem:
    """Nodes every `shooting_interval` samples; continuity gaps as equality constraints.

    Parameters
    ----------
    oem : OutputErrorModel
        The output-error model (compiled model, data, layout, options with ``shooting_interval``).

    Returns
    -------
    LeastSquaresProblem
        Decision vector [θ, every experiment's nodes] (scaled), known initial states fixed by bounds;
        in the structured form (its own compiled solver, the graph built on demand) where
        `structured.supports` it, else one CasADi graph with the gaps' curvature for the Hessian.
    """
    cm, layout = oem.cm, oem.layout
    node_sets = [_node_indices(d.n, oem.options.shooting_interval) for d in oem.data]
    node_offsets = list(layout.size + np.cumsum([0] + [cm.nx * ns.size for ns in node_sets])[:-1])
    lbw_x, ubw_x = _node_bounds(oem, node_sets)
    lo, hi = theta_bounds(layout)

    def x0_of(w: np.ndarray) -> list[dict[str, float]]:
        return [{s: float(w[node_offsets[e] + i] * oem.xscale[i]) for i, s in enumerate(cm.states)}
                for e in range(len(oem.data))]

    n_gap = sum(cm.nx * (ns.size - 1) for ns in node_sets)
    if shooting_structured.supports(oem):
        n_par = shooting_structured.constraint_count(oem)
        problem = LeastSquaresProblem(
            w=ca.MX.sym("w", layout.size + sum(cm.nx * ns.size for ns in node_sets)),
            residual_builder=lambda: None, g=ca.MX.sym("g", n_gap + n_par),
            lbg=np.concatenate([np.zeros(n_gap), shooting_structured.constraint_lower(oem)]),
            ubg=np.concatenate([np.zeros(n_gap), shooting_structured.constraint_upper(oem)]),
            lbw=np.concatenate([lo, *lbw_x]), ubw=np.concatenate([hi, *ubw_x]),
            n_theta=layout.size, initial_guess=_node_guess(oem, node_sets), x0_of=x0_of,
            graph_builder=lambda: _multiple_shooting_graph(oem, node_sets, node_offsets, x0_of))
        return shooting_structured.attach_solver(oem, problem)
    return _multiple_shooting_graph(oem, node_sets, node_offsets, x0_of)


def _multiple_shooting_graph(oem: OutputErrorModel, node_sets, node_offsets, x0_of) -> LeastSquaresProblem:
    """Multiple shooting as one CasADi graph, with the gaps' curvature for the Hessian."""
    cm, layout = oem.cm, oem.layout
    lbw_x, ubw_x = _node_bounds(oem, node_sets)
    lo, hi = theta_bounds(layout)
    n_gap = sum(cm.nx * (ns.size - 1) for ns in node_sets)
    theta = ca.MX.sym("theta", layout.size)
    w_parts, res, gaps = [theta], [], []
    curvature = GapCurvature(oem, MAP_MODE)
    xs = ca.DM(oem.xscale)
    for e, d in enumerate(oem.data):
        nodes = node_sets[e]
        xn_s = ca.MX.sym(f"X{e}", cm.nx, nodes.size)
        w_parts.append(ca.vec(xn_s))
        xn = ca.repmat(xs, 1, nodes.size) * xn_s
        p = layout.full(e, theta)
        if oem.options.shooting_interval == 1:
            # a node at every sample: contiguous slices only, outputs on the nodes themselves
            pred = oem.step.map(d.n - 1, MAP_MODE)(xn[:, :-1], d.u[:, :-1], d.u[:, 1:],
                                                   ca.repmat(p, 1, d.n - 1), d.t[None, :-1],
                                                   np.diff(d.t)[None, :])
            gaps.append((pred - xn[:, 1:]) / xs)
            curvature.add(e, node_offsets[e], np.arange(d.n - 1), 1, np.arange(d.n - 1))
            res.append(oem.residual_of(e, oem.outputs_of(e, xn, p)))
            continue
        lengths = np.diff(nodes)
        pieces = []
        # intervals come in at most two lengths (the last may be shorter): one map per length
        for length in sorted(set(lengths.tolist()), key=lambda L: np.flatnonzero(lengths == L)[0]):
            ks = np.flatnonzero(lengths == length)
            base = oem.simulator(int(length))
            sim = base.map(int(ks.size), MAP_MODE)
            cols = np.concatenate([np.arange(nodes[k], nodes[k] + length) for k in ks])
            pred = sim(xn[:, ks.tolist()], d.u[:, cols], d.u[:, cols + 1], ca.repmat(p, 1, cols.size),
                       d.t[cols][None, :], (d.t[cols + 1] - d.t[cols])[None, :])
            pieces.append(pred)
            ends = [(j + 1) * int(length) - 1 for j in range(ks.size)]
            gaps.append((pred[:, ends] - xn[:, (ks + 1).tolist()]) / xs)
            curvature.add(e, node_offsets[e], ks, int(length), cols)
        states = ca.horzcat(xn[:, 0], *pieces)
        res.append(oem.residual_of(e, oem.outputs_of(e, states, p)))

    g_par, lbg_par, ubg_par = parameter_constraints(cm, layout, theta)
    g = ca.vertcat(*[ca.vec(gp) for gp in gaps], *g_par)
    w = ca.vertcat(*[ca.vec(v) for v in w_parts])
    return LeastSquaresProblem(
        w=w, residual_builder=lambda: ca.vertcat(*res), g=g,
        lbg=np.concatenate([np.zeros(n_gap), *lbg_par]), ubg=np.concatenate([np.zeros(n_gap), *ubg_par]),
        lbw=np.concatenate([lo, *lbw_x]), ubw=np.concatenate([hi, *ubw_x]),
        n_theta=layout.size, initial_guess=_node_guess(oem, node_sets), x0_of=x0_of,
        extra_labels=[], constraint_hessian=curvature.bind(w, theta, g_par))
