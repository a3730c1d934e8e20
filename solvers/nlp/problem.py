"""The least-squares NLP every method builds: min ½‖r(w)‖² s.t. lbg ≤ g(w) ≤ ubg, lbw ≤ w ≤ ubw."""
from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property
from typing import TYPE_CHECKING, Callable

import casadi as ca
import numpy as np

from greyfit.schemas.fit import FitOptions
from greyfit.solvers.data.experiments import ExperimentData
from greyfit.solvers.errors import DataError
from greyfit.solvers.model.compiler import CompiledModel
from greyfit.solvers.model.parameters import ParameterLayout

if TYPE_CHECKING:   # the protocol module imports the solver, which imports this module
    from greyfit.solvers.nlp.protocol import SolverFactory


# weighted residuals beyond this overflow when squared and summed
WEIGHTED_LIMIT = 1e100


@dataclass
class LeastSquaresProblem:
    """Decision vector w = [θ (scaled parameters); method-specific variables]."""

    w: ca.MX
    residual_builder: Callable[[], ca.MX]   # built on first use: the closed-form path never needs it
    g: ca.MX
    lbg: np.ndarray
    ubg: np.ndarray
    lbw: np.ndarray
    ubw: np.ndarray
    n_theta: int
    initial_guess: Callable[[np.ndarray], np.ndarray]  # physical θ -> w0
    x0_of: Callable[[np.ndarray], list[dict[str, float]]]  # w -> initial states per experiment
    extra_labels: list[str] = field(default_factory=list)
    # numeric (J, r) at w; set where a cheaper form than differentiating the MX graph exists
    jacobian: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]] | None = None
    # extra residual rows of θ (scaled), e.g. a total-variation penalty; in the NLP only, not in
    # the data Jacobian used for the covariance
    penalty: Callable[[ca.MX], ca.MX] | None = None
    # a solver over a different formulation of the same NLP (e.g. structured multiple shooting);
    # `w` and `g` then only give the sizes, the residual graph is never built
    solver_factory: SolverFactory | None = None
    # w -> JᵀJ at w, where the solver computes it anyway at its first evaluation (folded single
    # shooting): the start checks ask for it there instead of a Jacobian of their own
    start_gram: Callable[[np.ndarray], np.ndarray] | None = None
    # (λ) -> the constraints' curvature added to the Gauss-Newton Hessian (multiple shooting)
    constraint_hessian: Callable[[ca.MX], ca.MX] | None = None
    # where `solver_factory` is a structured form: the same NLP as one CasADi graph, built when a
    # solver needs what only the graph has (the gaps' exact curvature)
    graph_builder: Callable[[], "LeastSquaresProblem"] | None = None
    _graph: "LeastSquaresProblem | None" = field(default=None, init=False, repr=False)

    def graph(self) -> "LeastSquaresProblem":
        """This problem as a CasADi graph (itself unless it is a structured form); same w, bounds.

        The graph is built once on first use and cached; the problem's `penalty` is attached to it on
        every call, since it is set after building (time-varying parameters).

        Returns
        -------
        LeastSquaresProblem
            `self` when no `graph_builder` is set, else the cached problem built by it.
        """
        if self.graph_builder is None:
            return self
        if self._graph is None:
            self._graph = self.graph_builder()
        self._graph.penalty = self.penalty   # attached after building (time-varying parameters)
        return self._graph

    @cached_property
    def residual(self) -> ca.MX:
        """Residual vector r(w) of the NLP, built on first use and cached.

        Returns
        -------
        casadi.MX
            Column of the residuals from `residual_builder`, with the `penalty` rows of the scaled θ
            (the first `n_theta` entries of w) appended below when a penalty is set.
        """
        r = self.residual_builder()
        return r if self.penalty is None else ca.vertcat(r, self.penalty(self.w[:self.n_theta]))

    def constraint_curvature(self, lam_g: ca.MX) -> ca.MX | None:
        """What the Gauss-Newton Hessian adds for the constraints (nlp.py): multiple shooting's
        gap curvature (solvers/methods/shooting/hybrid.py); None elsewhere (JᵀJ alone, as always).

        Parameters
        ----------
        lam_g : casadi.MX
            Symbolic multipliers of the constraints g, one per row of `g`.

        Returns
        -------
        casadi.MX or None
            The constraints' curvature as a symbolic (n_w, n_w) matrix, or None when the problem has no
            `constraint_hessian`.
        """
        return None if self.constraint_hessian is None else self.constraint_hessian(lam_g)

    def evaluate_jacobian(self, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Residual Jacobian and residuals evaluated numerically at a decision vector.

        Uses the problem's cheaper `jacobian` callable where one is set, else differentiates the
        residual graph with CasADi.

        Parameters
        ----------
        w : numpy.ndarray
            Decision vector, shape (n_w,).

        Returns
        -------
        jac : numpy.ndarray
            Jacobian dr/dw, shape (n_r, n_w).
        res : numpy.ndarray
            Residuals r(w), shape (n_r,).
        """
        if self.jacobian is not None:
            return self.jacobian(w)
        fn = ca.Function("residual_jacobian", [self.w], [ca.jacobian(self.residual, self.w), self.residual])
        jac, res = fn(w)
        return np.array(jac), np.array(res).ravel()


def parameter_constraints(cm: CompiledModel, layout: ParameterLayout, theta: ca.MX):
    """User constraints g(p) ≥ 0 (or = 0) applied to every experiment's parameter vector.

    When no parameter is per-experiment, the constraints are applied once (all experiments share
    the same parameter vector).

    Parameters
    ----------
    cm : CompiledModel
        Compiled model; its `constraint` function and `constraint_equality` mask are used.
    layout : ParameterLayout
        Maps the scaled decision θ to each experiment's full parameter vector.
    theta : casadi.MX
        Symbolic scaled parameter decision vector.

    Returns
    -------
    g : list of casadi.MX
        Constraint expressions, one per experiment (or one if all are shared); empty without constraints.
    lo : list of numpy.ndarray
        Lower bounds, zeros, one array per entry of `g`.
    hi : list of numpy.ndarray
        Upper bounds: 0 for equality constraints, +inf for inequalities, one array per entry of `g`.
    """
    if cm.constraint is None:
        return [], [], []
    g, lo, hi = [], [], []
    n_exp = len(layout.matrix)
    shared = all(e is None for e in layout.experiment)
    for e in range(1 if shared else n_exp):
        g.append(cm.constraint(layout.full(e, theta)))
        ng = cm.constraint_equality.size
        lo.append(np.zeros(ng))
        hi.append(np.where(cm.constraint_equality, 0.0, np.inf))
    return g, lo, hi


def theta_bounds(layout: ParameterLayout) -> tuple[np.ndarray, np.ndarray]:
    """Bounds of the scaled parameter decision vector θ.

    Parameters
    ----------
    layout : ParameterLayout
        Parameter layout holding physical `lower`, `upper` bounds and the `scale` of each entry of θ.

    Returns
    -------
    lower : numpy.ndarray
        Lower bounds divided by the scale, shape (n_theta,).
    upper : numpy.ndarray
        Upper bounds divided by the scale, shape (n_theta,).
    """
    return layout.lower / layout.scale, layout.upper / layout.scale


def output_weights(cm: CompiledModel, data: list[ExperimentData], options: FitOptions) -> np.ndarray:
    """Weight per output: user value, else 1/std of the measured output over all experiments.

    Parameters
    ----------
    cm : CompiledModel
        Compiled model; gives the outputs' names and count.
    data : list of ExperimentData
        Prepared experiments; the finite measured values of each output are pooled across them.
    options : FitOptions
        Fit options; `output_weights` maps an output name to a user weight.

    Returns
    -------
    numpy.ndarray
        One weight per output, shape (ny,). An output with zero spread (or one sample) gets weight 1.

    Raises
    ------
    DataError
        When a user weight times the largest measured magnitude exceeds `WEIGHTED_LIMIT` (its squares
        would overflow); names `options.output_weights.<output>`.
    """
    w = np.ones(cm.ny)
    for j, name in enumerate(cm.outputs):
        values = np.concatenate([d.y[j][np.isfinite(d.y[j])] for d in data])
        if name in options.output_weights:
            w[j] = options.output_weights[name]
            peak = w[j] * float(np.max(np.abs(values), initial=0.0))
            if peak > WEIGHTED_LIMIT:
                raise DataError(f"the weighted output reaches {peak:.1e}, its squares overflow; use a "
                                "smaller weight (only the ratios between outputs matter)",
                                f"options.output_weights.{name}")
            continue
        sd = float(np.std(values)) if values.size > 1 else 0.0
        w[j] = 1.0 / sd if sd > 0 else 1.0
    return w


def state_scales(cm: CompiledModel, data: list[ExperimentData]) -> np.ndarray:
    """O(1) scaling for state variables from the range of directly measured states.

    Parameters
    ----------
    cm : CompiledModel
        Compiled model; `direct_outputs` maps an output to the state it measures directly.
    data : list of ExperimentData
        Prepared experiments; the finite measured values are pooled across them.

    Returns
    -------
    numpy.ndarray
        One scale per state, shape (nx,): the largest absolute measured value of a directly
        measured state, else 1.
    """
    scale = np.ones(cm.nx)
    for out, state in cm.direct_outputs.items():
        j, i = cm.outputs.index(out), cm.states.index(state)
        values = np.concatenate([np.abs(d.y[j][np.isfinite(d.y[j])]) for d in data])
        if values.size and values.max() > 0:
            scale[i] = float(values.max())
    return scale
