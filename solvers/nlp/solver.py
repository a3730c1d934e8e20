"""Solve a LeastSquaresProblem with Ipopt (Gauss-Newton or exact Hessian), or in closed form."""
from __future__ import annotations

import time
from dataclasses import dataclass

import casadi as ca
import numpy as np

from greyfit.schemas.fit import FitOptions
from greyfit.solvers.nlp.problem import LeastSquaresProblem

SUCCESS_STATUSES = {"Solve_Succeeded", "Solved_To_Acceptable_Level", "Linear_Least_Squares"}


@dataclass
class NlpOutcome:
    w: np.ndarray
    cost: float
    status: str
    success: bool
    iterations: int
    wall_time_s: float
    # Ipopt's constraint violation at the returned iterate (multiple shooting: the largest gap in units
    # of the state's scale); 0 without constraints or where it is not reported
    infeasibility: float = 0.0


class LeastSquaresSolver:
    """Builds the Ipopt instance once; `solve(w0)` may be called for every multistart."""

    compiled = False   # CasADi evaluates the whole graph in its interpreter

    def __init__(self, problem: LeastSquaresProblem, options: FitOptions, curvature: bool = True,
                 ipopt: dict | None = None):
        """`curvature`: add the problem's constraint curvature to Gauss-Newton (multiple shooting);
        `ipopt`: extra Ipopt options (solvers/methods/shooting/hybrid.py)."""
        self.problem = problem
        w, r = problem.w, problem.residual
        nlp = {"x": w, "f": 0.5 * ca.sumsqr(r), "g": problem.g}
        opts = {
            "ipopt.max_iter": options.max_iter,
            "ipopt.max_cpu_time": options.max_cpu_time,
            "ipopt.tol": options.tol,
            "ipopt.print_level": 0,
            "ipopt.sb": "yes",
            "print_time": False,
            # a NaN or Inf at a trial point is Ipopt's to handle (it steps back) and the result's to
            # report; CasADi's line per evaluation on stderr only buried a library user's output
            "show_eval_warnings": False,
            **{f"ipopt.{k}": v for k, v in (ipopt or {}).items()},
        }
        if options.hessian == "gauss_newton":
            jac = ca.jacobian(r, w)
            sigma = ca.MX.sym("sigma")
            lam_g = ca.MX.sym("lam_g", problem.g.numel())
            hess = sigma * ca.mtimes(jac.T, jac)
            gap_curvature = problem.constraint_curvature(lam_g) if curvature else None
            if gap_curvature is not None:
                # multiple shooting: without its gaps' curvature the step is unstable when the
                # model misfits, and walked from the optimum to a degenerate point (#8)
                hess = hess + gap_curvature
            opts["hess_lag"] = ca.Function(
                "nlp_hess_l",
                {"x": w, "p": ca.MX.sym("p", 0), "lam_f": sigma, "lam_g": lam_g,
                 "hess_gamma_x_x": ca.triu(hess)},
                ["x", "p", "lam_f", "lam_g"], ["hess_gamma_x_x"])
        self.solver = ca.nlpsol("greyfit", "ipopt", nlp, opts)
        self.residual = ca.Function("residual", [w], [r])

    def solve(self, w0: np.ndarray, lbw: np.ndarray | None = None, ubw: np.ndarray | None = None) -> NlpOutcome:
        """From w0 (clipped into the bounds), within the problem's bounds or those given (a profile fixes
        one entry); a failed evaluation is an unsuccessful outcome, not an exception."""
        return run_ipopt(self.solver, w0, self.problem, lbw=lbw, ubw=ubw)


def run_ipopt(solver: ca.Function, w0: np.ndarray, problem: LeastSquaresProblem,
              p: np.ndarray | None = None, lbw: np.ndarray | None = None,
              ubw: np.ndarray | None = None) -> NlpOutcome:
    """One Ipopt solve from w0 (clipped into the bounds); an evaluation error is a failed outcome.

    Parameters
    ----------
    solver : casadi.Function
        An `nlpsol` instance built over the problem.
    w0 : numpy.ndarray
        Start decision vector, shape (n_w,).
    problem : LeastSquaresProblem
        Gives the default variable bounds and the constraint bounds `lbg`, `ubg`.
    p : numpy.ndarray or None, optional
        Values of the NLP's parameters, for solvers built with a parameter vector.
    lbw, ubw : numpy.ndarray or None, optional
        Variable bounds, shape (n_w,); None uses the problem's.

    Returns
    -------
    NlpOutcome
        Solution `w`, cost ½‖r‖², Ipopt's return status, success (status in `SUCCESS_STATUSES`),
        iteration count, wall time in seconds and the constraint violation at the iterate. When the
        solver raises a RuntimeError (e.g. CVODES fails at the start), `w` is the clipped start, the
        cost NaN and the status ``Evaluation_Failed: <reason>``.
    """
    lbw = problem.lbw if lbw is None else lbw
    ubw = problem.ubw if ubw is None else ubw
    w0 = np.clip(w0, lbw, ubw)
    start = time.perf_counter()
    args = dict(x0=w0, lbx=lbw, ubx=ubw, lbg=problem.lbg, ubg=problem.ubg)
    if p is not None:
        args["p"] = p
    try:
        sol = solver(**args)
    except RuntimeError as exc:   # e.g. CVODES cannot integrate at the start point
        reason = str(exc).strip().splitlines()[0][:200] if str(exc).strip() else "error"
        return NlpOutcome(w0, float("nan"), f"Evaluation_Failed: {reason}", False, 0,
                          time.perf_counter() - start)
    stats = solver.stats()
    w = np.array(sol["x"]).ravel()
    status = str(stats.get("return_status", "unknown"))
    violations = (stats.get("iterations") or {}).get("inf_pr") or [0.0]
    return NlpOutcome(w, float(sol["f"]), status, status in SUCCESS_STATUSES,
                      int(stats.get("iter_count", 0)), time.perf_counter() - start, float(violations[-1]))


def solve_linear_least_squares(problem: LeastSquaresProblem, options: FitOptions) -> NlpOutcome | None:
    """Closed-form solution when the residual is affine in θ and no bound or constraint is active.

    Returns None when the unconstrained optimum violates a bound or a constraint (Ipopt then
    solves the convex QP), and when the regressors are not finite or too large for the SVD (values
    near the float limits): Ipopt then ends the fit with a status that says so.

    Parameters
    ----------
    problem : LeastSquaresProblem
        A problem whose residual is affine in w; its Jacobian and residual at w = 0 give the
        regressors A and offset b (r = A w + b).
    options : FitOptions
        Fit options (unused by the closed form; kept for the solver call signature).

    Returns
    -------
    NlpOutcome or None
        The least-squares solution with status ``Linear_Least_Squares`` and zero iterations, or None
        as described above.
    """
    start = time.perf_counter()
    w = problem.w
    a, b = problem.evaluate_jacobian(np.zeros(w.numel()))
    if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
        return None
    try:
        sol, *_ = np.linalg.lstsq(a, -b, rcond=None)
    except np.linalg.LinAlgError:   # "SVD did not converge": entries near 1e308 overflow inside it
        return None
    if not np.all(np.isfinite(sol)):
        return None
    feasible = np.all(sol >= problem.lbw - 1e-12) and np.all(sol <= problem.ubw + 1e-12)
    if problem.g.numel():
        gval = np.array(ca.Function("g", [w], [problem.g])(sol)).ravel()
        feasible = feasible and np.all(gval >= problem.lbg - 1e-9) and np.all(gval <= problem.ubg + 1e-9)
    if not feasible:
        return None
    r = a @ sol + b
    return NlpOutcome(sol, 0.5 * float(r @ r), "Linear_Least_Squares", True, 0,
                      time.perf_counter() - start)
