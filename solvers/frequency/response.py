"""Evaluate polynomials at s = jω as linear maps of their coefficient vectors.

``P(jω_i) = V[i] @ c`` with ``V[i, k] = (jω_i)^(n-k)``. Dividing every row by ``max(1, ω_i)^n``
keeps the numbers in range for high degrees and high frequencies; a common row scale of numerator
and denominator does not change their ratio.
"""
from __future__ import annotations

import casadi as ca
import numpy as np


def vandermonde(omega: np.ndarray, degree: int, row_scale: np.ndarray | None = None) -> np.ndarray:
    """Complex (N, degree+1) matrix of (jω)^(degree-k), optionally divided by `row_scale`.

    Parameters
    ----------
    omega : numpy.ndarray
        (N,) angular frequencies, rad/s.
    degree : int
        Polynomial degree n.
    row_scale : numpy.ndarray or None
        (N,) divisor of each row (`row_scale`); None: unscaled.

    Returns
    -------
    numpy.ndarray
        Complex (N, n+1) V with V[i, k] = (jω_i)^(n-k) / row_scale[i], so V @ c is P(jω) for
        coefficients c in descending powers.
    """
    powers = np.arange(degree, -1, -1)
    v = (1j * omega[:, None]) ** powers[None, :]
    return v if row_scale is None else v / row_scale[:, None]


def row_scale(omega: np.ndarray, degree: int) -> np.ndarray:
    """Row divisor max(1, ω)^degree that keeps high-degree, high-frequency rows in range.

    Parameters
    ----------
    omega : numpy.ndarray
        (N,) angular frequencies, rad/s.
    degree : int
        Polynomial degree (take the denominator's, and use the same scale for the numerator).

    Returns
    -------
    numpy.ndarray
        (N,) positive scale factors.
    """
    return np.maximum(1.0, omega) ** degree


def evaluate_polynomial(coefficients, omega: np.ndarray, scale: np.ndarray | None = None):
    """(real, imag) of the polynomial at jω; numpy in, numpy out; CasADi in, CasADi out.

    Parameters
    ----------
    coefficients : array_like or casadi.SX or casadi.MX or casadi.DM
        (n+1,) coefficients in descending powers of s.
    omega : numpy.ndarray
        (N,) angular frequencies, rad/s.
    scale : numpy.ndarray or None
        (N,) row divisor (`row_scale`); None: unscaled.

    Returns
    -------
    tuple
        (real part, imaginary part) of P(jω)/scale, each (N,) numpy or an (N, 1) CasADi column.
    """
    n = (coefficients.numel() if hasattr(coefficients, "numel") else len(coefficients)) - 1
    v = vandermonde(omega, n, scale)
    if isinstance(coefficients, (ca.SX, ca.MX, ca.DM)):
        return ca.mtimes(ca.DM(v.real), coefficients), ca.mtimes(ca.DM(v.imag), coefficients)
    c = np.asarray(coefficients, dtype=float)
    return v.real @ c, v.imag @ c


def closed_loop_response(num, den, omega: np.ndarray):
    """(real, imag) of num(jω)/den(jω) as CasADi expressions (or numpy) of the coefficients.

    Parameters
    ----------
    num, den : array_like or casadi.SX or casadi.MX or casadi.DM
        Numerator and denominator coefficients, descending powers of s.
    omega : numpy.ndarray
        (N,) angular frequencies, rad/s.

    Returns
    -------
    tuple
        (real part, imaginary part) of the ratio at each ω, numpy (N,) or CasADi (N, 1) like the input.
    """
    n_den = (den.numel() if hasattr(den, "numel") else len(den)) - 1
    scale = row_scale(omega, n_den)
    nr, ni = evaluate_polynomial(num, omega, scale)
    dr, di = evaluate_polynomial(den, omega, scale)
    mag = dr * dr + di * di
    return (nr * dr + ni * di) / mag, (ni * dr - nr * di) / mag


def numeric_response(num: np.ndarray, den: np.ndarray, omega: np.ndarray) -> np.ndarray:
    """The complex response num(jω)/den(jω) of numeric coefficients.

    Parameters
    ----------
    num, den : numpy.ndarray
        Numerator and denominator coefficients, descending powers of s.
    omega : numpy.ndarray
        (N,) angular frequencies, rad/s.

    Returns
    -------
    numpy.ndarray
        (N,) complex response.
    """
    re, im = closed_loop_response(np.asarray(num, float), np.asarray(den, float), omega)
    return np.asarray(re).ravel() + 1j * np.asarray(im).ravel()
