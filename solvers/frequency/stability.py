"""Stability of a closed loop: Liénard-Chipart (Routh-Hurwitz) conditions and a pole check.

For ``D(s) = a0 s^n + a1 s^(n-1) + ... + an`` with ``a0 > 0``, all roots lie in the open left half
plane iff (Liénard-Chipart) every coefficient is positive and the Hurwitz minors
``Δ_(n-1), Δ_(n-3), ...`` are positive. These are polynomial in the coefficients, hence smooth
constraints for Ipopt (Routh's first column is their ratio ``Δ_k / Δ_(k-1)``). Before forming them,
s is rescaled by a constant σ so that the nominal coefficients are O(1): stability does not change
under ``s -> σ z`` with σ > 0, and the margin ε then means the same for every loop.
"""
from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

MAX_SYMBOLIC_DEGREE = 8   # symbolic Hurwitz determinants grow fast; above this only the poles are checked


@dataclass
class HurwitzConditions:
    """h(p) >= margin for stability; `labels` say which coefficient or minor each entry is."""

    expressions: list        # SX scalars of p
    labels: list[str]
    constant_violation: str | None = None   # a condition that no parameter value can satisfy


def hurwitz_matrix(a: list) -> list[list]:
    """n×n Hurwitz matrix H[i][j] = a_(2j - i + 1) (0-based i, j), zero outside 0..n.

    Parameters
    ----------
    a : list
        n+1 coefficients a0..an in descending powers of s (SX scalars or floats).

    Returns
    -------
    list of list
        The n×n matrix as nested lists, entries of the same kind as `a`.
    """
    n = len(a) - 1
    zero = ca.SX(0) if isinstance(a[0], ca.SX) else 0.0
    return [[a[2 * j - i + 1] if 0 <= 2 * j - i + 1 <= n else zero for j in range(n)] for i in range(n)]


def normalised(den: list, nominal: np.ndarray) -> list:
    """Coefficients of D(σ z) / (|a0| σ^n) with σ and |a0| taken from the nominal values.

    Parameters
    ----------
    den : list
        n+1 coefficients of D(s), descending powers (SX scalars or floats).
    nominal : numpy.ndarray
        (n+1,) the same coefficients at nominal parameter values; σ = (|an|/|a0|)^(1/n).

    Returns
    -------
    list
        The n+1 rescaled coefficients; stability is unchanged since σ > 0.
    """
    n = len(den) - 1
    a0 = abs(nominal[0]) if nominal[0] != 0 else 1.0
    an = abs(nominal[-1])
    sigma = (an / a0) ** (1.0 / n) if n > 0 and an > 0 else 1.0
    return [den[k] / (a0 * sigma ** k) for k in range(n + 1)]


def lienard_chipart(den: list, nominal: np.ndarray, depends_on) -> HurwitzConditions:
    """Conditions on the SX coefficients `den` (descending); `depends_on(expr)` tells constants apart.

    Above `MAX_SYMBOLIC_DEGREE` only the coefficient conditions are formed.

    Parameters
    ----------
    den : list
        n+1 SX coefficients of the closed-loop denominator, descending powers of s.
    nominal : numpy.ndarray
        (n+1,) their values at the nominal parameters (for the rescaling of `normalised`).
    depends_on : callable
        ``depends_on(expr) -> bool``: whether an expression depends on the free parameters.

    Returns
    -------
    HurwitzConditions
        The positive-coefficient and Hurwitz-minor expressions with their labels, or, when a constant
        coefficient is not positive, no expressions and `constant_violation` saying which.
    """
    a = normalised(den, nominal)
    n = len(a) - 1
    exprs, labels = [], []
    for k in range(n + 1):
        if depends_on(a[k]):
            exprs.append(a[k])
            labels.append(f"coefficient of s^{n - k}")
        elif float(ca.evalf(a[k])) <= 0:
            return HurwitzConditions([], [], f"the coefficient of s^{n - k} is {float(ca.evalf(den[k]))} "
                                     "whatever the parameters: the loop cannot be stable")
    if n > MAX_SYMBOLIC_DEGREE:
        return HurwitzConditions(exprs, labels)
    h = hurwitz_matrix(a)
    for k in range(n - 1, 1, -2):
        minor = ca.det(ca.SX(ca.vertcat(*[ca.horzcat(*row[:k]) for row in h[:k]])))
        exprs.append(minor)
        labels.append(f"Hurwitz minor Δ{k}")
    return HurwitzConditions(exprs, labels)


def routh_first_column(den: np.ndarray) -> list[float]:
    """Routh array's first column (numeric); a zero pivot is replaced by a tiny ε as in textbooks.

    Parameters
    ----------
    den : numpy.ndarray
        Denominator coefficients, descending powers of s (leading zeros are dropped).

    Returns
    -------
    list of float
        The n+1 first-column entries; all of one sign iff every root is in the open left half plane.
    """
    a = np.trim_zeros(np.asarray(den, dtype=float), "f")
    n = a.size - 1
    if n < 1:
        return [float(a[0])] if a.size else []
    rows = [a[0::2].copy(), a[1::2].copy()]
    width = rows[0].size
    rows = [np.pad(r, (0, width - r.size)) for r in rows]
    eps = 1e-12 * max(1.0, float(np.max(np.abs(a))))
    for _ in range(n - 1):
        up, low = rows[-2], rows[-1]
        pivot = low[0] if low[0] != 0 else eps
        new = np.zeros(width)
        new[:-1] = (pivot * up[1:] - up[0] * low[1:]) / pivot
        rows.append(new)
    return [float(r[0]) for r in rows]


def poles(den: np.ndarray) -> np.ndarray:
    """Roots of the denominator; NaN (one, unknown) where its coefficients are not finite, e.g. a
    constant near the float limits overflowed them: such a loop is not reported stable.

    Parameters
    ----------
    den : numpy.ndarray
        Denominator coefficients, descending powers of s (leading zeros are dropped).

    Returns
    -------
    numpy.ndarray
        Complex roots (empty for a constant); one NaN when the coefficients are not finite or the
        eigenvalue computation failed.
    """
    a = np.trim_zeros(np.asarray(den, dtype=float), "f")
    if not np.all(np.isfinite(a)):
        return np.array([complex(np.nan, np.nan)])
    try:
        return np.roots(a) if a.size > 1 else np.zeros(0, dtype=complex)
    except np.linalg.LinAlgError:   # the companion matrix's eigenvalues did not converge
        return np.array([complex(np.nan, np.nan)])


def is_stable(den: np.ndarray) -> bool:
    """Whether every pole has a negative real part.

    Parameters
    ----------
    den : numpy.ndarray
        Denominator coefficients, descending powers of s.

    Returns
    -------
    bool
        True when all poles are in the open left half plane (or there are none); False when any is
        not, or the poles are unknown (NaN).
    """
    p = poles(den)
    return bool(p.size == 0 or np.max(p.real) < 0)
