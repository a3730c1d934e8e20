"""Design criteria on the information matrix: D, A and E-optimality of a subset of the parameters.

The criteria are written on the relative information D F D (D = diag|θ|), so that a parameter in
N s/m and one in kg weigh alike, and on the covariance of the parameters of interest only (the others
are nuisance: their uncertainty still counts through the inverse). Inverse and determinant come from
a Cholesky factor written out in SX: the matrices are small (≤ a few tens), and CasADi's own `det`
expands cofactors.
"""
from __future__ import annotations

import math

import casadi as ca
import numpy as np

# relative ridge on the information: a design that leaves a parameter unseen gets a large, finite
# criterion (and a gradient that points to exciting it) instead of log 0
RIDGE = 1e-10
# E-optimality: the largest eigenvalue of the covariance as the trace of its 2^k-th power's root
E_POWER_DOUBLINGS = 3
# the whitened ΔBIC the discovery loop needs to name one law over another (its AMBIGUOUS_BIC; a test
# keeps the two equal without the design importing the loop)
SETTLE_BIC = 10.0
SETTLE_PROBABILITY = 0.9      # the chance a record should give of settling the closest pair
_Z_SETTLE = 1.2815515655446004   # Φ⁻¹(0.9)


def settle_probability(divergence: float, penalty: float, margin: float = SETTLE_BIC) -> float:
    """The chance that a record settles a pair: its realised ΔBIC above `margin`.

    On a record the rival's χ² exceeds the truth's by the divergence D (the noise-free gap) plus a
    cross term 2·Σ gap·noise/σ², which is normal with variance 4D; ΔBIC adds the parameter-count
    `penalty`. So P = Φ((D + penalty − margin) / (2√D)), to first order in the refits' own noise.

    Parameters
    ----------
    divergence : float
        Σ((y_truth − y_rival)/σ)² with the rival refitted (D).
    penalty : float
        (rival's free parameters − truth's)·ln N.
    margin : float, optional
        The ΔBIC that settles it (the loop's ambiguity margin).

    Returns
    -------
    float
        A probability in [0, 1].
    """
    if divergence <= 0:
        return 0.0 if penalty <= margin else 1.0
    z = (divergence + penalty - margin) / (2.0 * math.sqrt(divergence))
    return 0.5 * math.erfc(-z / math.sqrt(2.0))


def divergence_to_settle(penalty: float, margin: float = SETTLE_BIC) -> float:
    """The divergence at which `settle_probability` reaches `SETTLE_PROBABILITY`.

    Parameters
    ----------
    penalty : float
        (rival's free parameters − truth's)·ln N.
    margin : float, optional
        The ΔBIC that settles it.

    Returns
    -------
    float
        D with (D + penalty − margin)/(2√D) = Φ⁻¹(0.9): √D = z + √(z² + margin − penalty); 0 when the
        penalty alone settles it.
    """
    slack = _Z_SETTLE ** 2 + margin - penalty
    return 0.0 if slack <= 0 else (_Z_SETTLE + math.sqrt(slack)) ** 2


def _cholesky(a: ca.SX) -> ca.SX:
    n = a.shape[0]
    L = ca.SX.zeros(n, n)
    for j in range(n):
        d = a[j, j] - sum((L[j, k] ** 2 for k in range(j)), ca.SX(0))
        L[j, j] = ca.sqrt(d)
        for i in range(j + 1, n):
            L[i, j] = (a[i, j] - sum((L[i, k] * L[j, k] for k in range(j)), ca.SX(0))) / L[j, j]
    return L


def _inverse(a: ca.SX) -> ca.SX:
    L = _cholesky(a)
    Li = ca.solve(L, ca.SX.eye(a.shape[0]))   # triangular: SX's solve stays exact and small
    return Li.T @ Li


def criterion_function(kind: str, nth: int, interest: list[int]) -> ca.Function:
    """Function (F, scale) -> the criterion to minimise.

    Parameters
    ----------
    kind : str
        "D" (log det of the covariance of interest), "A" (its trace) or "E" (its largest eigenvalue,
        smoothly approximated).
    nth : int
        Size of F (the free parameters).
    interest : list of int
        Positions of the parameters of interest among the free ones.

    Returns
    -------
    casadi.Function
        F (nth × nth, absolute information), scale (nth: |θ|) -> scalar.
    """
    F, scale = ca.SX.sym("F", nth, nth), ca.SX.sym("scale", nth)
    rel = ca.diag(scale) @ F @ ca.diag(scale)
    rel = 0.5 * (rel + rel.T) + RIDGE * (ca.trace(rel) / nth + 1e-300) * ca.SX.eye(nth)
    cov = _inverse(rel)[interest, interest]
    if kind == "D":
        value = 2 * ca.sum1(ca.log(ca.diag(_cholesky(cov))))
    elif kind == "A":
        value = ca.trace(cov)
    elif kind == "E":
        power = cov / ca.trace(cov)
        for _ in range(E_POWER_DOUBLINGS):
            power = power @ power
        value = ca.trace(cov) * ca.trace(power) ** (1.0 / 2 ** E_POWER_DOUBLINGS)
    else:
        raise ValueError(f"unknown criterion {kind!r}")
    return ca.Function(f"criterion_{kind}", [F, scale], [value])


def criterion_value(kind: str, information: np.ndarray, scale: np.ndarray, interest: list[int]) -> float:
    """The exact criterion of a numeric information matrix (E: the largest eigenvalue itself).

    Parameters
    ----------
    kind : str
        "D", "A" or "E".
    information : ndarray
        The absolute information matrix of the free parameters.
    scale : ndarray
        |θ| of the free parameters.
    interest : list of int
        Positions of the parameters of interest.

    Returns
    -------
    float
        The criterion (inf where the information is singular).
    """
    rel = np.diag(scale) @ information @ np.diag(scale)
    try:
        cov = np.linalg.inv(0.5 * (rel + rel.T))[np.ix_(interest, interest)]
    except np.linalg.LinAlgError:
        return float("inf")
    if kind == "D":
        sign, logdet = np.linalg.slogdet(cov)
        return float(logdet) if sign > 0 else float("inf")
    if kind == "A":
        return float(np.trace(cov))
    return float(np.max(np.linalg.eigvalsh(cov)))


def predicted_stderrs(information: np.ndarray) -> np.ndarray | None:
    """Standard errors sqrt(diag F⁻¹), or None where F is singular.

    Parameters
    ----------
    information : ndarray
        The absolute information matrix.

    Returns
    -------
    ndarray or None
    """
    try:
        cov = np.linalg.inv(0.5 * (information + information.T))
    except np.linalg.LinAlgError:
        return None
    d = np.diag(cov)
    if not np.all(np.isfinite(d)) or np.any(d <= 0):
        return None
    return np.sqrt(d)
