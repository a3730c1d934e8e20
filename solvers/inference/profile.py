"""Profile-likelihood intervals for named parameters (`options.profile`), as pyPESTO and D2D do.

For a parameter θ_i the profile is c_PL(v) = min over the other variables of the cost with θ_i
fixed to v (every other parameter and free initial state re-optimised, warm-started from the
previous point). The interval is where c_PL rises less than

    Δ = ½ t²(ν; (1 + level)/2) σ²,   σ² = 2 ĉ / ν,   ν = ndata − nvarys,

the likelihood-ratio test with the noise variance estimated from the residual (as lmfit's
conf_interval and D2D's "chi2" mode do); t² = F(1, ν) makes it exact for a linear model with
Gaussian noise (where it equals the Wald interval) and tends to χ²(1) for large ν. Unlike the
Wald interval θ ± t·stderr it follows the cost where it is not quadratic: asymmetric, or open
towards a bound when the data cannot exclude it.

Steps adapt so that each raises the cost by about Δ/4 (doubled when it rose by less than Δ/10,
halved above Δ/2); once a step passes the threshold, the crossing is found by regula falsi on
√(rise), exact for a quadratic profile, with up to REFINE more solves.

The walk is bounded by counts only (MAX_STEPS steps and MAX_FAILURES unconverged points per side,
REFINE solves per crossing), so an interval does not depend on machine load. `max_cpu_time` (CPU
seconds for all the profiles of a fit) is a safety net: when it runs out, or a re-optimisation hits
Ipopt's own CPU limit, that parameter's profile and the ones after it are reported as not computed
(no ends, no points) with a note saying so, never as an interval a quiet machine would not give.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from greyfit.schemas.fit import ProfileInterval
from greyfit.solvers.errors import DataError
from greyfit.solvers.inference.statistics import student_t_quantile
from greyfit.solvers.nlp.problem import LeastSquaresProblem
from greyfit.solvers.nlp.protocol import Solver

MAX_STEPS = 20        # per side
REFINE = 4            # solves to locate a crossing
TOLERANCE = 0.02      # of Δ, at the crossing
MAX_FAILURES = 3      # unconverged re-optimisations on one side before giving up there
CPU_LIMIT_STATUS = "Maximum_CpuTime_Exceeded"   # Ipopt's, for one re-optimisation


class _CpuLimitReached(Exception):
    """The profiles' safety net ended a walk: no interval for this parameter."""


@dataclass
class ProfileContext:
    problem: LeastSquaresProblem
    solver: Solver        # make_warm_solver's: re-optimisations start next to the optimum
    w_hat: np.ndarray     # the fit's NLP solution (scaled)
    cost_hat: float       # the NLP objective there
    scale: np.ndarray     # physical = scaled * scale, per θ entry
    ndata: int
    nvarys: int
    level: float
    max_cpu_time: float
    notes: list[str] = field(default_factory=list)


def check_profile_names(names: list[str], labels: list[str]) -> None:
    """Check that every name in `options.profile` is a free parameter of the fit.

    Parameters
    ----------
    names : list of str
        The requested parameter names (`options.profile`).
    labels : list of str
        The free parameters' labels (per-experiment copies as ``name[experiment]``).

    Raises
    ------
    DataError
        On the first name that is not a free parameter; names ``options.profile[k]``.
    """
    for k, name in enumerate(names):
        if name not in labels:
            raise DataError(f"'{name}' is not a free parameter (free: {labels}); profile a free parameter "
                            "(per-experiment copies as name[experiment])", f"options.profile[{k}]")


def colour_adjustment(cov) -> dict[str, float]:
    """Per parameter, var_HAC / var_classical where the residual is coloured (the HAC covariance is
    reported), else nothing.

    The likelihood-ratio threshold assumes white noise: under coloured residuals the cost rises
    faster than the information the data hold, and the profile interval is as narrow as the
    classical Wald interval (coverage 41-65 % measured in issue 22). Scaling the threshold by this
    ratio (an adjusted likelihood ratio, Chandler & Bate 2007) makes a quadratic profile's interval
    the HAC interval, and keeps the profile's asymmetry elsewhere.

    Parameters
    ----------
    cov : CovarianceEstimate
        The fit's covariance; its `robust_bandwidth` is set when the HAC covariance is reported.

    Returns
    -------
    dict of str to float
        (se_HAC / se_classical)² per parameter with both standard errors finite and non-zero; empty
        when the classical covariance is reported.
    """
    if cov.robust_bandwidth is None:
        return {}
    out = {}
    for name, se in cov.stderr.items():
        classical = cov.classical_stderr.get(name)
        if se and classical and math.isfinite(se) and math.isfinite(classical):
            out[name] = (se / classical) ** 2
    return out


def profile_parameters(ctx: ProfileContext, names: list[str], labels: list[str],
                       stderr: dict[str, float | None],
                       adjustment: dict[str, float] | None = None) -> dict[str, ProfileInterval]:
    """Profile interval of each of `names`; `adjustment`: per name, the factor the threshold is
    scaled by (`colour_adjustment`).

    Parameters
    ----------
    ctx : ProfileContext
        The problem, a warm solver, the NLP solution and cost, the parameter scales, the data and
        variable counts, the confidence level and the CPU-time budget.
    names : list of str
        Parameters to profile; each must be in `labels`.
    labels : list of str
        Label of each scaled θ entry.
    stderr : dict of str to float or None
        Classical standard error per label (physical units); sets the first step, else 10 % of
        max(|θ̂|, 1) in scaled units.
    adjustment : dict of str to float or None, optional
        Per name, the factor the threshold ½t²σ² is scaled by.

    Returns
    -------
    dict of str to ProfileInterval
        Per name: the interval ends (None where the profile stays below the threshold), the visited
        values (physical units) and re-optimised costs, the threshold, notes and the adjustment used.
        Without a degree of freedom or a finite cost, an empty profile with a note; once the CPU
        limit has run out, an empty profile whose note says so.
    """
    adjustment = adjustment or {}
    dof = ctx.ndata - ctx.nvarys
    out = {}
    start = time.process_time()
    for name in names:
        i = labels.index(name)
        if dof <= 0 or not math.isfinite(ctx.cost_hat):
            out[name] = ProfileInterval(lower=None, upper=None, values=[], costs=[], threshold=None,
                                        note="no degree of freedom or no finite cost: no profile")
            continue
        t = student_t_quantile(0.5 + ctx.level / 2, dof)
        factor = adjustment.get(name)
        delta = 0.5 * t * t * (2.0 * ctx.cost_hat / dof) * (factor or 1.0)
        se = stderr.get(name)
        h0 = se / ctx.scale[i] if se is not None and math.isfinite(se) and se > 0 else \
            0.1 * max(abs(ctx.w_hat[i]), 1.0)
        points = [(float(ctx.w_hat[i]), ctx.cost_hat)]
        ends, notes = [], []
        try:
            for direction in (-1.0, 1.0):
                end, pts, note = _walk(ctx, i, direction, h0, delta, start)
                ends.append(end)
                points += pts
                if note:
                    notes.append(note)
        except _CpuLimitReached:
            ctx.notes = []
            out[name] = ProfileInterval(
                lower=None, upper=None, values=[], costs=[], threshold=ctx.cost_hat + delta,
                note=f"not computed: the CPU limit of the profiles (options.max_cpu_time = {ctx.max_cpu_time:g} s) "
                     "ran out, a safety net; the walk itself is bounded by its steps, so raise max_cpu_time",
                noise_adjustment=factor)
            continue
        points.sort()
        notes += ctx.notes
        ctx.notes = []
        if factor is not None:
            notes.append(f"the residual is coloured: the threshold is scaled by the HAC/classical variance "
                         f"ratio {factor:.3g} (adjusted likelihood ratio), so that the interval allows for it; "
                         "unadjusted it would assume white noise")
        lower, upper = ends
        out[name] = ProfileInterval(
            lower=None if lower is None else lower * ctx.scale[i],
            upper=None if upper is None else upper * ctx.scale[i],
            values=[v * ctx.scale[i] for v, _ in points], costs=[c for _, c in points],
            threshold=ctx.cost_hat + delta, note="; ".join(notes) or None, noise_adjustment=factor)
    return out


def _solve_fixed(ctx: ProfileContext, i: int, v: float, w_start: np.ndarray):
    lbw, ubw = ctx.problem.lbw.copy(), ctx.problem.ubw.copy()
    lbw[i] = ubw[i] = v
    w0 = w_start.copy()
    w0[i] = v
    out = ctx.solver.solve(w0, lbw=lbw, ubw=ubw)
    if out.status == CPU_LIMIT_STATUS:
        raise _CpuLimitReached
    return out


def _walk(ctx: ProfileContext, i: int, direction: float, h0: float, delta: float, start: float):
    """(crossing in scaled units or None, [(value, cost)], note) on one side of the estimate;
    raises _CpuLimitReached when the CPU limit (since `start`) has run out."""
    bound = ctx.problem.lbw[i] if direction < 0 else ctx.problem.ubw[i]
    side = "lower" if direction < 0 else "upper"
    v_prev, rise_prev, w_prev = float(ctx.w_hat[i]), 0.0, ctx.w_hat
    h, failures = h0, 0
    pts: list[tuple[float, float]] = []   # (scaled value, cost)
    for _ in range(MAX_STEPS):
        if time.process_time() - start > ctx.max_cpu_time:
            raise _CpuLimitReached
        if v_prev == bound:
            return None, pts, f"the cost stays below the threshold up to the {side} bound"
        v = v_prev + direction * h
        if np.isfinite(bound) and (v - bound) * direction > 0:
            v = float(bound)
        out = _solve_fixed(ctx, i, v, w_prev)
        if not (out.success and np.isfinite(out.cost)):
            # an unconverged point's cost is no profile value (multiple shooting: gaps still open)
            failures += 1
            if failures >= MAX_FAILURES:
                return None, pts, (f"{side} end: the re-optimisation did not converge at "
                                   f"{v * ctx.scale[i]:.6g} ({out.status})")
            h /= 4
            continue
        rise = out.cost - ctx.cost_hat
        pts.append((v, float(out.cost)))
        if rise < -TOLERANCE * delta:
            ctx.notes.append(f"the profile found a lower cost ({out.cost:.6g} < {ctx.cost_hat:.6g}) at "
                             f"{v * ctx.scale[i]:.6g}: the fit is not at the optimum")
        if rise >= delta:
            crossing, more = _refine(ctx, i, (v_prev, rise_prev, w_prev), (v, rise, out.w), delta)
            return crossing, pts + more, None
        gain = rise - rise_prev
        h = h * 2 if gain < delta / 10 else h / 2 if gain > delta / 2 else h
        v_prev, rise_prev, w_prev = v, max(rise, 0.0), out.w
    return None, pts, f"{side} end not reached in {MAX_STEPS} steps"


def _refine(ctx: ProfileContext, i: int, inside, outside, delta: float):
    """Regula falsi on s(v) = √rise − √Δ between a point inside and one outside the interval."""
    (v_in, r_in, w_in), (v_out, r_out, _) = inside, outside
    target = math.sqrt(delta)
    pts = []
    v = v_out
    for _ in range(REFINE):
        s_in, s_out = math.sqrt(max(r_in, 0.0)), math.sqrt(r_out)
        v = v_in + (target - s_in) / (s_out - s_in) * (v_out - v_in) if s_out > s_in else 0.5 * (v_in + v_out)
        out = _solve_fixed(ctx, i, v, w_in)
        if not (out.success and np.isfinite(out.cost)):
            break
        rise = out.cost - ctx.cost_hat
        pts.append((v, float(out.cost)))
        if abs(rise - delta) <= TOLERANCE * delta:
            break
        if rise < delta:
            v_in, r_in, w_in = v, rise, out.w
        else:
            v_out, r_out = v, rise
    return v, pts


def run_profiles(problem, options, outcome, layout, ndata: int, nvarys: int, cov) -> dict | None:
    """`result.profile` for `options.profile` (None when empty); called by `fit_model`.

    Parameters
    ----------
    problem : LeastSquaresProblem
        The fit's NLP.
    options : FitOptions
        Fit options: `profile`, `confidence_level`, `max_cpu_time` and the solver settings.
    outcome : NlpOutcome
        The fit's NLP solution.
    layout : ParameterLayout
        The parameter layout (labels and scales of θ).
    ndata : int
        Number of residuals.
    nvarys : int
        Number of fitted variables.
    cov : CovarianceEstimate
        The fit's covariance: its classical standard errors set the first steps, its HAC ones the
        threshold adjustment.

    Returns
    -------
    dict of str to ProfileInterval or None
        As `profile_parameters`; None when `options.profile` is empty.
    """
    if not options.profile:
        return None
    from greyfit.solvers.methods.shooting.hybrid import make_warm_solver
    ctx = ProfileContext(problem, make_warm_solver(problem, options), np.asarray(outcome.w, dtype=float),
                         float(outcome.cost), layout.scale, ndata, nvarys, options.confidence_level,
                         options.max_cpu_time)
    stderr = {k: cov.classical_stderr.get(k, cov.stderr.get(k)) for k in layout.labels}
    return profile_parameters(ctx, list(options.profile), list(layout.labels), stderr, colour_adjustment(cov))
