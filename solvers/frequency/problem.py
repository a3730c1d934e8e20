"""The frequency-domain least-squares problem: residual per cost, user and Routh-Hurwitz constraints."""
from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from greyfit.schemas.frequency import FrequencyFitOptions
from greyfit.solvers.errors import ModelDefinitionError
from greyfit.solvers.frequency.data import FrequencySet
from greyfit.solvers.frequency.polynomials import ClosedLoop, CompiledTransferFunction
from greyfit.solvers.frequency.response import closed_loop_response
from greyfit.solvers.frequency.stability import lienard_chipart
from greyfit.solvers.model.parameters import ParameterLayout
from greyfit.solvers.nlp.problem import LeastSquaresProblem


@dataclass
class FrequencyProblem:
    problem: LeastSquaresProblem
    n_data_rows: int                  # residual rows that are data (the rest is the stability penalty)
    data_residual: ca.Function        # θ (scaled) -> data residual
    stability_labels: list[str]       # one per Hurwitz condition (all loops)
    stability: ca.Function | None     # θ -> Hurwitz conditions (normalised; >= margin when stable)
    notes: list[str]
    user_constraint: tuple[ca.Function, np.ndarray, np.ndarray] | None = None   # θ -> g, lbg, ubg


def data_weights(sets: list[FrequencySet], cost: str) -> list[np.ndarray]:
    """Per-frequency weight of the complex error: 1/|G| (relative) or one common 1/rms|G|.

    The common factor of `complex` and `log1p_abs_error` only scales the cost (not its minimiser) so that
    Ipopt's tolerances see an O(1) problem.

    Parameters
    ----------
    sets : list of FrequencySet
        The prepared data sets.
    cost : str
        The cost (`options.cost`): "relative_complex" weighs each frequency by 1/|G|; any other cost
        gets one common 1/rms|G| over all sets (1 when every response is zero).

    Returns
    -------
    list of numpy.ndarray
        One (N_e,) weight array per data set.
    """
    if cost == "relative_complex":
        return [1.0 / np.maximum(np.abs(s.response), 1e-300) for s in sets]
    rms = float(np.sqrt(np.mean(np.concatenate([np.abs(s.response) ** 2 for s in sets]))))
    return [np.full(s.omega.size, 1.0 / rms if rms > 0 else 1.0) for s in sets]


def cost_residual(re, im, g: np.ndarray, weight: np.ndarray, cost: str):
    """Residual rows of one data set (CasADi) for the chosen cost.

    Parameters
    ----------
    re, im : casadi.MX or casadi.SX
        (N, 1) real and imaginary parts of the model's response at the set's frequencies.
    g : numpy.ndarray
        (N,) complex measured response G(jω).
    weight : numpy.ndarray
        (N,) weights from `data_weights` (not used by "log", whose rows are relative already).
    cost : str
        "log": log-magnitude and phase of model/measured; "log1p_abs_error": the error pair d scaled
        so that its squared norm is w²·log(1 + |d|)² (w the common weight); else ("complex",
        "relative_complex") the weighted real and imaginary errors.

    Returns
    -------
    casadi.MX or casadi.SX
        (2N, 1) residual column: the N real-part rows, then the N imaginary-part (or phase) rows.
    """
    gr, gi = g.real, g.imag
    if cost == "log":
        mag2 = np.abs(g) ** 2
        qr = (re * gr + im * gi) / mag2
        qi = (im * gr - re * gi) / mag2
        return ca.vertcat(0.5 * ca.log(qr * qr + qi * qi), ca.atan2(qi, qr))
    dr, di = re - gr, im - gi
    if cost == "log1p_abs_error":
        # the row pair (dr, di) * log(1+|d|)/|d| has squared norm log(1+|d|)^2 exactly, but is smooth at
        # d = 0, and its Gauss-Newton Hessian keeps the curvature across d that a scalar |d| row loses
        tiny = (1e-12 / weight[0]) ** 2
        m = ca.sqrt(dr * dr + di * di + tiny)
        ratio = weight[0] * ca.log1p(m) / m
        return ca.vertcat(dr * ratio, di * ratio)
    return ca.vertcat(dr * weight, di * weight)


def _distinct_parameter_vectors(layout: ParameterLayout) -> list[int]:
    shared = all(e is None for e in layout.experiment)
    return [0] if shared else list(range(len(layout.matrix)))


def build_frequency_problem(tf: CompiledTransferFunction, loops: list[ClosedLoop], stability_loops:
                            list[tuple[ClosedLoop, int]], sets: list[FrequencySet], layout: ParameterLayout,
                            options: FrequencyFitOptions) -> FrequencyProblem:
    """Decision vector = scaled θ only; `stability_loops` pairs each loop with its parameter set index.

    Parameters
    ----------
    tf : CompiledTransferFunction
        The compiled model (its user constraints g(p) and the parameter symbol).
    loops : list of ClosedLoop
        The measured loop of each data set, in the order of `sets`.
    stability_loops : list of tuple of (ClosedLoop, int)
        Loops whose stability is required, each with the index of the parameter vector it uses.
    sets : list of FrequencySet
        The prepared data sets.
    layout : ParameterLayout
        The free parameters (scales, bounds, per-set parameter vectors).
    options : FrequencyFitOptions
        Cost, stability handling ("routh": Liénard-Chipart constraints ≥ margin, "penalty": a residual
        penalty, else none), stability margin and penalty weight.

    Returns
    -------
    FrequencyProblem
        The least-squares problem over scaled θ, the number of data rows, the data residual and
        Hurwitz Functions, the condition labels, notes and the user constraint (or None).

    Raises
    ------
    ModelDefinitionError
        When a loop's denominator has a constant coefficient that is not positive: no parameter values
        can make it stable (`model.feedback`).
    """
    theta = ca.MX.sym("theta", layout.size)
    weights = data_weights(sets, options.cost)
    rows = []
    for e, (loop, s) in enumerate(zip(loops, sets)):
        p = layout.full(e, theta)
        re, im = closed_loop_response(loop.num_fn(p), loop.den_fn(p), s.omega)
        rows.append(cost_residual(re, im, s.response, weights[e], options.cost))
    data_r = ca.vertcat(*rows)

    g, lbg, ubg, notes = [], [], [], []
    if tf.constraint is not None:
        fn = ca.Function("user_g", [tf.p], [tf.constraint])
        for e in _distinct_parameter_vectors(layout):
            g.append(fn(tf.arguments(layout.full(e, theta))))
            lbg.append(np.zeros(tf.constraint_equality.size))
            ubg.append(np.where(tf.constraint_equality, 0.0, np.inf))

    user = None
    if g:
        user = (ca.Function("user_g", [theta], [ca.vertcat(*g)]), np.concatenate(lbg), np.concatenate(ubg))
    p0 = [layout.full(e, layout.initial / layout.scale) for e in range(len(layout.matrix))]
    h_rows, labels = [], []
    if options.stability in ("routh", "penalty"):
        for loop, e in stability_loops:
            nominal = np.array(loop.den_fn(p0[e])).ravel()
            cond = lienard_chipart(loop.den, nominal, lambda x: ca.depends_on(x, tf.p))
            if cond.constant_violation:
                raise ModelDefinitionError(f"loop '{loop.name}': {cond.constant_violation}", "model.feedback")
            if not cond.expressions:
                continue
            fn = ca.Function("hurwitz", [tf.p], [ca.vertcat(*cond.expressions)])
            h_rows.append(fn(tf.arguments(layout.full(e, theta))))
            labels += [f"{loop.name}: {lab}" for lab in cond.labels]
            if len(loop.den) - 1 > 8:
                notes.append(f"loop '{loop.name}' has degree {len(loop.den) - 1}: only coefficient signs are "
                             "constrained; stability is checked from the poles")
    h = ca.vertcat(*h_rows) if h_rows else None
    margin = options.stability_margin
    residual = data_r
    if h is not None and options.stability == "routh":
        g.append(h)
        lbg.append(np.full(h.numel(), margin))
        ubg.append(np.full(h.numel(), np.inf))
    elif h is not None:
        residual = ca.vertcat(data_r, np.sqrt(options.penalty_weight) * ca.fmax(0, margin - h))

    lbw, ubw = layout.lower / layout.scale, layout.upper / layout.scale
    problem = LeastSquaresProblem(
        w=theta, residual_builder=lambda: residual, g=ca.vertcat(*g) if g else ca.MX(0, 1),
        lbg=np.concatenate(lbg) if lbg else np.zeros(0), ubg=np.concatenate(ubg) if ubg else np.zeros(0),
        lbw=lbw, ubw=ubw, n_theta=layout.size,
        initial_guess=lambda theta_phys: np.asarray(theta_phys, float) / layout.scale,
        x0_of=lambda w: [{} for _ in sets])
    return FrequencyProblem(problem, int(data_r.numel()), ca.Function("data_r", [theta], [data_r]), labels,
                            ca.Function("hurwitz", [theta], [h]) if h is not None else None, notes, user)
