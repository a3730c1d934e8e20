"""Time-varying parameters in batch fits (seed 000's k4(t)): θ(t) = Σ_j B_j(t) v_j.

A parameter declared with `time_varying` is replaced by one parameter per segment (piecewise
constant) or per knot (piecewise linear), named `<name>__<j>`; the compiled model is wrapped so
that its equations see θ(t) at the time they are evaluated (equation error: the samples; shooting:
every integrator stage). A total-variation penalty enters as extra residual rows
√(2Wn)·Δ/(Δ² + ε²)^¼, so that ½ r² = W·n·Δ²/√(Δ² + ε²) ≈ W·n·|Δ| (n data samples, Δ the relative
change of the value, or of the slope for piecewise linear; ε = 1e-4): steps stay steps. Unlike
√|Δ| rows, these have a nonzero Jacobian at Δ = 0, so the Gauss-Newton Hessian stays regular.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, replace

import casadi as ca
import numpy as np

from greyfit.schemas.model import Model
from greyfit.schemas.online import ParameterTrajectory, TimeVarying
from greyfit.solvers.data.experiments import ExperimentData
from greyfit.solvers.errors import ModelDefinitionError
from greyfit.solvers.model.compiler import CompiledModel
from greyfit.solvers.model.parameters import ParameterLayout

TV_EPSILON = 1e-4
IRLS_STATUS = "IRLS_Converged"


@dataclass
class VaryingParameter:
    name: str
    spec: TimeVarying
    knots: np.ndarray
    names: list[str]             # the expanded parameters, in order

    def basis(self, t) -> list:
        """B_j(t) for CasADi or numpy t.

        Piecewise constant: the indicator of each segment between knots; piecewise linear: the hat
        function of each knot (the first and last held flat outside the knot range).

        Parameters
        ----------
        t : casadi.SX or casadi.MX or numpy.ndarray or float
            Time(s) to evaluate at.

        Returns
        -------
        list
            One basis value (or expression / array like `t`) per expanded parameter, in `names` order.
        """
        k = self.knots
        fmin = ca.fmin if isinstance(t, (ca.SX, ca.MX)) else np.minimum
        fmax = ca.fmax if isinstance(t, (ca.SX, ca.MX)) else np.maximum
        if self.spec.kind == "piecewise_constant":
            steps = [1.0 * (t >= k[j]) for j in range(1, len(self.names))]     # Heaviside at inner knots
            ones = [1.0 + 0 * t]
            cum = ones + steps
            return [cum[j] - (cum[j + 1] if j + 1 < len(cum) else 0 * t) for j in range(len(cum))]
        out = []
        for j in range(len(k)):
            up = 1.0 + 0 * t if j == 0 else fmin(fmax((t - k[j - 1]) / (k[j] - k[j - 1]), 0), 1)
            down = 1.0 + 0 * t if j == len(k) - 1 else fmin(fmax((k[j + 1] - t) / (k[j + 1] - k[j]), 0), 1)
            out.append(fmin(up, down))
        return out

    def differences(self, v):
        """Relative first differences (constant) or slope changes x span (linear) of the values v.

        Parameters
        ----------
        v : sequence
            The expanded parameters' values (numbers or CasADi expressions), in `names` order; scaled
            values make the differences relative to the guess.

        Returns
        -------
        list
            n − 1 first differences for piecewise constant; n − 2 changes of slope, each slope taken
            over the whole knot span, for piecewise linear.
        """
        if self.spec.kind == "piecewise_constant":
            return [v[j + 1] - v[j] for j in range(len(self.names) - 1)]
        span = self.knots[-1] - self.knots[0]
        slopes = [(v[j + 1] - v[j]) / (self.knots[j + 1] - self.knots[j]) * span for j in range(len(self.knots) - 1)]
        return [slopes[j + 1] - slopes[j] for j in range(len(slopes) - 1)]


@dataclass
class TimeVaryingExpansion:
    model: Model                 # parameters expanded (for the layout)
    cm: CompiledModel            # equations in the expanded parameters
    varying: list[VaryingParameter]
    n_samples: int

    def penalty(self, layout: ParameterLayout):
        """Extra residual rows (θ scaled -> rows) for the total-variation terms, or None.

        Parameters
        ----------
        layout : ParameterLayout
            Layout of the expanded parameters (their labels locate each varying parameter's values).

        Returns
        -------
        callable or None
            Maps the scaled θ (CasADi) to the rows √(2Wn)·Δ/(Δ² + ε²)^¼ of every parameter with a
            total-variation regularisation of positive weight; None when there is none.
        """
        parts = [(vp, [layout.labels.index(n) for n in vp.names]) for vp in self.varying
                 if vp.spec.regularization == "total_variation" and vp.spec.weight > 0]
        if not parts:
            return None

        def rows(theta):
            out = []
            for vp, idx in parts:
                # scaled values are relative to the guess: Δ is a relative change
                for d in vp.differences([theta[i] for i in idx]):
                    out.append(np.sqrt(2 * vp.spec.weight * self.n_samples) * d / (d ** 2 + TV_EPSILON ** 2) ** 0.25)
            return ca.vertcat(*out)
        return rows

    def difference_matrix(self, layout: ParameterLayout) -> tuple[np.ndarray, np.ndarray]:
        """(D, c): the differences Δ = Dθ (θ scaled; they are linear in θ) and each row's weight W n.

        Parameters
        ----------
        layout : ParameterLayout
            Layout of the expanded parameters.

        Returns
        -------
        d : numpy.ndarray
            Difference matrix, shape (n_differences, n_theta); (0, n_theta) without a penalty.
        c : numpy.ndarray
            Weight W·n of each row, shape (n_differences,).
        """
        blocks, weights = [], []
        eye = np.eye(layout.size)
        for vp in self.varying:
            if vp.spec.regularization != "total_variation" or vp.spec.weight <= 0:
                continue
            idx = [layout.labels.index(n) for n in vp.names]
            cols = [np.array(vp.differences([eye[i][j] for i in idx]), dtype=float) for j in range(layout.size)]
            blocks.append(np.column_stack(cols))
            weights.append(np.full(blocks[-1].shape[0], vp.spec.weight * self.n_samples))
        if not blocks:
            return np.zeros((0, layout.size)), np.zeros(0)
        return np.vstack(blocks), np.concatenate(weights)

    def solve_affine(self, problem, layout: ParameterLayout, max_iter: int = 200):
        """Iteratively reweighted least squares for an affine residual plus the TV penalty.

        min ½‖Jθ + r₀‖² + Σ_j c_j √(Δ_j² + ε²), Δ = Dθ: each iteration solves
        (JᵀJ + Dᵀ diag(c/√(Δ² + ε²)) D) θ = −Jᵀr₀; the problem is convex, so this converges to
        its optimum (from the unpenalised least-squares start). Returns None when a bound is
        violated (Ipopt then solves it) or there is no penalty.

        Parameters
        ----------
        problem : LeastSquaresProblem
            The fit's NLP, with a residual affine in the scaled θ.
        layout : ParameterLayout
            Layout of the expanded parameters.
        max_iter : int, optional
            Largest number of reweighting iterations.

        Returns
        -------
        tuple of (NlpOutcome, int) or None
            The outcome (status ``IRLS_Converged``, the penalised cost, the iterations done) and the
            number of starts used (1); or None as above.
        """
        from greyfit.solvers.nlp.solver import NlpOutcome
        d, c = self.difference_matrix(layout)
        if d.shape[0] == 0:
            return None
        started = time.perf_counter()
        jac, r0 = problem.evaluate_jacobian(np.zeros(layout.size))
        jtj, jtr = jac.T @ jac, jac.T @ r0
        ridge = 1e-14 * float(np.mean(np.diag(jtj))) * np.eye(layout.size)
        theta = np.linalg.lstsq(jac, -r0, rcond=None)[0]
        iterations = 0   # counted, not the loop variable: the outcome reports it after the loop
        for _ in range(max_iter):
            iterations += 1
            wts = c / np.sqrt((d @ theta) ** 2 + TV_EPSILON ** 2)
            new = np.linalg.solve(jtj + d.T @ (wts[:, None] * d) + ridge, -jtr)
            done = np.max(np.abs(new - theta)) <= 1e-10 * max(1.0, np.max(np.abs(new)))
            theta = new
            if done:
                break
        if np.any(theta < problem.lbw - 1e-12) or np.any(theta > problem.ubw + 1e-12):
            return None
        r = jac @ theta + r0
        cost = 0.5 * float(r @ r) + float(np.sum(c * np.sqrt((d @ theta) ** 2 + TV_EPSILON ** 2)))
        return NlpOutcome(theta, cost, IRLS_STATUS, True, iterations, time.perf_counter() - started), 1

    def trajectory(self, layout: ParameterLayout, theta: np.ndarray, cov_names: list[str],
                   cov: np.ndarray | None, times: np.ndarray) -> ParameterTrajectory:
        """θ(t) with a ±2σ band of each time-varying parameter on the given times.

        Parameters
        ----------
        layout : ParameterLayout
            Layout of the expanded parameters.
        theta : numpy.ndarray
            Fitted expanded parameters in physical units, shape (n_theta,).
        cov_names : list of str
            Names of the rows and columns of `cov`.
        cov : numpy.ndarray or None
            Covariance of the fitted parameters (physical units); None: no band.
        times : numpy.ndarray
            Times to evaluate θ(t) at, shape (N,).

        Returns
        -------
        ParameterTrajectory
            Values and ±2σ bounds per parameter (bounds None where the covariance misses a value) and a
            description of the expansion.
        """
        values, lower, upper = {}, {}, {}
        for vp in self.varying:
            idx = [layout.labels.index(n) for n in vp.names]
            basis = np.column_stack(vp.basis(times))                        # (N, nv)
            v = basis @ theta[idx]
            values[vp.name] = v.tolist()
            if cov is not None and all(n in cov_names for n in vp.names):
                ci = [cov_names.index(n) for n in vp.names]
                sd = np.sqrt(np.maximum(np.einsum("ki,ij,kj->k", basis, cov[np.ix_(ci, ci)], basis), 0))
                lower[vp.name], upper[vp.name] = (v - 2 * sd).tolist(), (v + 2 * sd).tolist()
            else:
                lower[vp.name] = upper[vp.name] = [None] * times.size
        kinds = ", ".join(f"{vp.name}: {vp.spec.kind} on {len(vp.names)} values, {vp.spec.regularization}"
                          + (f" (weight {vp.spec.weight:g})" if vp.spec.regularization != "none" else "")
                          for vp in self.varying)
        return ParameterTrajectory(estimator=f"batch fit with time-varying parameters ({kinds})",
                                   time=times.tolist(), values=values, lower=lower, upper=upper,
                                   note="band: ±2σ from the data-only covariance of the segment values")


def _knots(spec: TimeVarying, t0: float, t1: float) -> np.ndarray:
    if spec.knots is not None:
        return np.array(spec.knots, dtype=float)
    return np.linspace(t0, t1, (spec.segments or 1) + 1)   # the schema requires one of the two


def expand_time_varying(model: Model, cm: CompiledModel, data: list[ExperimentData]) -> TimeVaryingExpansion | None:
    """The expanded model and compiled Functions, or None when no parameter varies.

    Parameters
    ----------
    model : Model
        The model; parameters with `time_varying` are expanded into ``<name>__<j>``.
    cm : CompiledModel
        Its compiled form.
    data : list of ExperimentData
        The experiments; their overall time span places the default knots.

    Returns
    -------
    TimeVaryingExpansion or None
        The model with expanded parameters, a compiled model whose equations see θ(t), the varying
        parameters and the total number of samples; None when no parameter is time-varying.

    Raises
    ------
    ModelDefinitionError
        When a time-varying parameter is fixed or per experiment, an expanded name is already a
        parameter (``model.parameters[i].time_varying``), or a constraint involves a time-varying
        parameter (``model.constraints``).
    """
    declared = [(i, p) for i, p in enumerate(model.parameters) if p.time_varying is not None]
    if not declared:
        return None
    t0 = min(float(d.t[0]) for d in data)
    t1 = max(float(d.t[-1]) for d in data)
    taken = {p.name for p in model.parameters}
    new_params, varying = [], []
    for i, p in enumerate(model.parameters):
        if p.time_varying is None:
            new_params.append(p)
            continue
        where = f"model.parameters[{i}].time_varying"
        if p.fixed or p.per_experiment:
            raise ModelDefinitionError("a time-varying parameter can be neither fixed nor per_experiment", where)
        knots = _knots(p.time_varying, t0, t1)
        count = len(knots) - 1 if p.time_varying.kind == "piecewise_constant" else len(knots)
        names = [f"{p.name}__{j}" for j in range(count)]
        clash = sorted(set(names) & taken)
        if clash:
            raise ModelDefinitionError(f"'{clash[0]}' is already a parameter; rename it", where)
        new_params += [p.model_copy(update={"name": n, "time_varying": None}) for n in names]
        varying.append(VaryingParameter(p.name, p.time_varying, knots, names))
    if cm.constraint is not None:
        ps = ca.SX.sym("p", cm.np)
        tv_idx = [cm.parameters.index(vp.name) for vp in varying]
        if ca.depends_on(cm.constraint(ps), ps[tv_idx]):
            raise ModelDefinitionError("constraints on a time-varying parameter are not supported", "model.constraints")

    # p (declared order) as a function of the expanded vector p' and t
    new_names = [p.name for p in new_params]
    pe, t = ca.SX.sym("p", len(new_names)), ca.SX.sym("t")
    by_name = {vp.name: vp for vp in varying}
    p_of = []
    for name in cm.parameters:
        if name in by_name:
            vp = by_name[name]
            p_of.append(sum(b * pe[new_names.index(n)] for b, n in zip(vp.basis(t), vp.names)))
        else:
            p_of.append(pe[new_names.index(name)])
    p_expr = ca.vertcat(*p_of)
    x, u = ca.SX.sym("x", cm.nx), ca.SX.sym("u", cm.nu)
    rhs = ca.Function("rhs", [x, u, pe, t], [cm.rhs(x, u, p_expr, t)], ["x", "u", "p", "t"], ["dx"])
    out = ca.Function("output", [x, u, pe, t], [cm.output(x, u, p_expr, t)], ["x", "u", "p", "t"], ["y"])
    constraint = None
    if cm.constraint is not None:     # independent of the varying parameters (checked above)
        constraint = ca.Function("g", [pe], [ca.substitute(cm.constraint(p_expr), t, 0)])
    new_cm = replace(cm, parameters=new_names, rhs=rhs, output=out, constraint=constraint)
    new_model = model.model_copy(update={"parameters": new_params})
    return TimeVaryingExpansion(new_model, new_cm, varying, sum(d.n for d in data))
