"""Evaluate polynomials at s = jω as linear maps of their coefficient vectors.

``P(jω_i) = V[i] @ c`` with ``V[i, k] = (jω_i)^(n-k)``. Dividing every row by ``max(1, ω_i)^n``
keeps the numbers in range for high degrees and high frequencies; a common row scale of numerator
and denominator does not change their ratio.
"""
from __future__ import annotations

import casadi as ca
import numpy as np


def vandermonde(omega: np.ndarray, degree: int, row_scale: np.ndarray | None = None) -> np.ndarray:
    """Complex (N, degree+1) matrix of (jω)^(degree-k), optionally divided by `row_scale`."""
    powers = np.arange(degree, -1, -1)
    v = (1j * omega[:, None]) ** powers[None, :]
    return v if row_scale is None else v / row_scale[:, None]


def row_scale(omega: np.ndarray, degree: int) -> np.ndarray:
    return np.maximum(1.0, omega) ** degree


def evaluate_polynomial(coefficients, omega: np.ndarray, scale: np.ndarray | None = None):
    """(real, imag) of the polynomial at jω; numpy in, numpy out; CasADi in, CasADi out."""
    n = (coefficients.numel() if hasattr(coefficients, "numel") else len(coefficients)) - 1
    v = vandermonde(omega, n, scale)
    if isinstance(coefficients, (ca.SX, ca.MX, ca.DM)):
        return ca.mtimes(ca.DM(v.real), coefficients), ca.mtimes(ca.DM(v.imag), coefficients)
    c = np.asarray(coefficients, dtype=float)
    return v.real @ c, v.imag @ c


def closed_loop_response(num, den, omega: np.ndarray):
    """(real, imag) of num(jω)/den(jω) as CasADi expressions (or numpy) of the coefficients."""
    n_den = (den.numel() if hasattr(den, "numel") else len(den)) - 1
    scale = row_scale(omega, n_den)
    nr, ni = evaluate_polynomial(num, omega, scale)
    dr, di = evaluate_polynomial(den, omega, scale)
    mag = dr * dr + di * di
    return (nr * dr + ni * di) / mag, (ni * dr - nr * di) / mag


def numeric_response(num: np.ndarray, den: np.ndarray, omega: np.ndarray) -> np.ndarray:
    re, im = closed_loop_response(np.asarray(num, float), np.asarray(den, float), omega)
    return np.asarray(re).ravel() + 1j * np.asarray(im).ravel()
