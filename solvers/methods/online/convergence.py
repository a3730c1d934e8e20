"""Has an online estimate converged? The parameter trajectory and the output error at the end of the record.

An online estimator returns its last estimate whatever happened before it. It is an answer only
when the estimator has settled there:

* **the parameter trajectory settled**: over the last `TAIL` of the record each physical parameter
  neither drifts (the means of the tail's two halves differ by more than `DRIFT_RELATIVE` of its
  value: still converging, e.g. an adaptive law with a small gain) nor wanders (its standard
  deviation over the tail above `SPREAD_RELATIVE` of its value: the estimator follows noise, as a
  forgetting window with too little excitation does, and its last value is one draw of that
  spread: within 2·5 % = 10 % of where it settles); a parameter that changes in the record is
  judged where it has settled at its new value;
* **the output error not growing**: the RMS of the error (RLS's innovations, MRAS's state error)
  over the last eighth of the record at most `ERROR_RATIO` times that of the eighth before it: a
  growing error is an estimator drifting away (a falling one is still converging, which the
  parameters' drift shows where it matters: after a step in R the error falls for seconds while R
  is already within 0.1 %);
* **the estimate is precise enough to be right**: a parameter whose standard error is above
  `UNCERTAIN_RELATIVE` of its value (RLS's standard error for MRAS, which has none of its own: the
  same data hold the same information) is not determined to 10 % by the record
  (`parameter_uncertain`);
* **MRAS agrees with RLS** on the same regression where both apply (`disagreement_warnings`): the
  gradient law of MRAS converges to the least-squares answer on a persistently exciting input
  with a positive-real error system, and where it does not (a higher-order plant with P = I, gains
  too high or too low for the record) its estimate differs from RLS's by more than RLS's
  uncertainty.
"""
from __future__ import annotations

import numpy as np

from greyfit.schemas.fit import FitWarning

TAIL = 0.25                # the share of the record at its end that is judged
DRIFT_RELATIVE = 0.03      # change of the mean over the tail, relative to the value
SPREAD_RELATIVE = 0.05     # standard deviation over the tail, relative to the value
ERROR_RATIO = 2.0          # last eighth's error RMS against the eighth before: within this factor
MIN_TAIL_POINTS = 8
UNCERTAIN_RELATIVE = 0.05  # a standard error above this share of the value: ±2σ wider than ±10 %
DISAGREE_RELATIVE = 0.1    # MRAS and RLS differ by more than this share ...
DISAGREE_SIGMAS = 3.0      # ... and more than this many of RLS's standard errors


def unsettled_parameters(values: np.ndarray, labels: list[str]) -> dict[str, dict[str, float]]:
    """The parameters whose trajectory drifts or wanders over the record's tail.

    Parameters
    ----------
    values : numpy.ndarray
        (K, nθ) physical estimates over the record's tail (its last `TAIL`), in time order.
    labels : list of str
        The parameters' names.

    Returns
    -------
    dict of str to dict
        Per unsettled parameter: its relative drift and spread over the tail; empty when all settled or
        the tail has fewer than `MIN_TAIL_POINTS` samples.
    """
    tail = values
    if tail.shape[0] < MIN_TAIL_POINTS:
        return {}
    half = tail.shape[0] // 2
    out = {}
    for k, label in enumerate(labels):
        col = tail[:, k]
        size = abs(float(col[-1]))
        if not np.all(np.isfinite(col)) or size == 0:
            continue
        drift = abs(float(np.mean(col[half:]) - np.mean(col[:half]))) / size
        spread = float(np.std(col)) / size
        if drift > DRIFT_RELATIVE or spread > SPREAD_RELATIVE:
            out[label] = {"drift": drift, "spread": spread}
    return out


def error_trend(errors: np.ndarray) -> float | None:
    """RMS of the error over the last eighth of the record over that of the eighth before.

    Parameters
    ----------
    errors : numpy.ndarray
        (M, neq) the estimator's errors, one row per update.

    Returns
    -------
    float or None
        The ratio; None with fewer than 16 updates or an error that is zero throughout both eighths.
    """
    m = errors.shape[0]
    eighth = m // 8
    if eighth < 2:
        return None
    last = float(np.sqrt(np.nanmean(errors[m - eighth:] ** 2)))
    before = float(np.sqrt(np.nanmean(errors[m - 2 * eighth:m - eighth] ** 2)))
    if before == 0 and last == 0:
        return None
    return last / before if before > 0 else float("inf")


def settling_warnings(values: np.ndarray, labels: list[str], errors: np.ndarray) -> list[FitWarning]:
    """`estimate_not_settled` when the parameter trajectory or the output error has not settled.

    Parameters
    ----------
    values : numpy.ndarray
        (K, nθ) physical estimates over the record's tail (its last `TAIL`), in time order.
    labels : list of str
        The parameters' names.
    errors : numpy.ndarray
        (M, neq) the estimator's errors per update.

    Returns
    -------
    list of FitWarning
        One warning naming the unsettled parameters (drift and spread) and the error's trend; else empty.
    """
    moving = unsettled_parameters(values, labels)
    ratio = error_trend(errors)
    error_moving = ratio is not None and ratio > ERROR_RATIO
    if not moving and not error_moving:
        return []
    parts = [f"'{k}' drifts by {100 * v['drift']:.1f} % and wanders by {100 * v['spread']:.1f} %"
             for k, v in moving.items()]
    if error_moving:
        parts.append(f"the output error's RMS grew {ratio:.2g}-fold over the last eighth")
    return [FitWarning(
        code="estimate_not_settled",
        message=f"the online estimate has not settled over the last {100 * TAIL:.0f} % of the record ("
                + "; ".join(parts) + f"; settled means a drift within {100 * DRIFT_RELATIVE:g} % and a spread within "
                f"{100 * SPREAD_RELATIVE:g} %): the last value is "
                "not a converged answer; use a longer or richer record, a smaller forgetting (a longer memory) "
                "or other adaptation gains",
        detail={"parameters": moving, "error_ratio": ratio, "tail": TAIL, "drift_limit": DRIFT_RELATIVE,
                "spread_limit": SPREAD_RELATIVE})]


def disagreement_warnings(labels: list[str], mras: np.ndarray, rls: np.ndarray,
                          rls_stderr: np.ndarray | None) -> list[FitWarning]:
    """`estimate_not_settled` where MRAS's final estimate differs from RLS's on the same regression.

    Parameters
    ----------
    labels : list of str
        The parameters' names.
    mras, rls : numpy.ndarray
        (nθ,) the final physical estimates of MRAS and of RLS.
    rls_stderr : numpy.ndarray or None
        (nθ,) RLS's standard errors (None: the relative difference alone decides).

    Returns
    -------
    list of FitWarning
        One warning naming the parameters that differ by more than `DISAGREE_RELATIVE` of RLS's value
        and `DISAGREE_SIGMAS` of its standard errors; else empty.
    """
    sd = np.zeros_like(rls) if rls_stderr is None else np.where(np.isfinite(rls_stderr), rls_stderr, np.inf)
    gap = np.abs(mras - rls)
    off = (gap > DISAGREE_RELATIVE * np.abs(rls)) & (gap > DISAGREE_SIGMAS * sd) & np.isfinite(rls)
    if not np.any(off):
        return []
    named = {labels[k]: {"mras": float(mras[k]), "rls": float(rls[k])} for k in np.flatnonzero(off)}
    text = ", ".join(f"'{k}' {v['mras']:.4g} against {v['rls']:.4g}" for k, v in named.items())
    return [FitWarning(
        code="estimate_not_settled",
        message=f"MRAS and recursive least squares on the same data disagree ({text}; more than "
                f"{100 * DISAGREE_RELATIVE:g} % and {DISAGREE_SIGMAS:g} of RLS's standard errors): the adaptive law "
                "has not converged to the least-squares answer (gains, or an error system that is not "
                "positive real); compare with method recursive_least_squares",
        detail={"parameters": named, "relative": DISAGREE_RELATIVE, "sigmas": DISAGREE_SIGMAS})]


def uncertainty_warnings(labels: list[str], values: np.ndarray, stderr: np.ndarray | None) -> list[FitWarning]:
    """`parameter_uncertain` for the parameters whose standard error exceeds `UNCERTAIN_RELATIVE` of the value.

    Parameters
    ----------
    labels : list of str
        The parameters' names.
    values : numpy.ndarray
        (nθ,) the final physical estimates.
    stderr : numpy.ndarray or None
        (nθ,) their standard errors (RLS's for MRAS); None: nothing to judge.

    Returns
    -------
    list of FitWarning
        One warning naming each such parameter with its relative standard error; else empty.
    """
    if stderr is None:
        return []
    with np.errstate(divide="ignore", invalid="ignore"):
        rel = np.where(np.isfinite(stderr), stderr / np.abs(values), np.inf)
    wide = {labels[k]: float(rel[k]) for k in np.flatnonzero(rel > UNCERTAIN_RELATIVE)}
    if not wide:
        return []
    text = ", ".join(f"'{k}' ± {100 * v:.0f} %" for k, v in wide.items())
    return [FitWarning(
        code="parameter_uncertain",
        message=f"the record determines {text} (one standard error): wider than ±{100 * UNCERTAIN_RELATIVE:g} %, so "
                "the online estimate may be more than 10 % off; use a longer memory (forgetting closer to 1), "
                "a longer or richer record, or a batch method",
        detail={"relative_stderr": wide, "limit": UNCERTAIN_RELATIVE})]
