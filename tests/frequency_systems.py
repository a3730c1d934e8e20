"""Seed 001's closed loop as a truth system, simulated with scipy only (independent of greyfit).

Plant ``P(s) = (b1 s² + b2) / (s (s³ + a1 s² + a2 s + a3))`` under ``C(s) = Kp + Ki/s``; measured
``G = P / (1 + P C)``.
"""
from __future__ import annotations

import numpy as np
from scipy import linalg, signal

NAMES = ("a1", "a2", "a3", "b1", "b2")
# our truth: positive, a1*a2 = 48 > a3 = 25 (Routh), closed loop stable for (1, 1) and (1.65, 0),
# the zero sqrt(b2/b1) = 3.46 rad/s lies between grid points (a zero on a grid point makes |G| ~ 0 there)
TRUTH = {"a1": 4.0, "a2": 12.0, "a3": 25.0, "b1": 2.0, "b2": 24.0}
OMEGA = np.logspace(-1, 3, 41)


def closed_loop(p: dict, kp: float, ki: float) -> tuple[np.ndarray, np.ndarray]:
    plant_num = np.array([p["b1"], 0.0, p["b2"]])
    plant_den = np.polymul([1.0, 0.0], [1.0, p["a1"], p["a2"], p["a3"]])
    c_num, c_den = np.array([kp, ki]), np.array([1.0, 0.0])
    num = np.polymul(plant_num, c_den)
    den = np.polyadd(np.polymul(plant_den, c_den), np.polymul(plant_num, c_num))
    return num, den


def response(p: dict, kp: float, ki: float, omega: np.ndarray) -> np.ndarray:
    num, den = closed_loop(p, kp, ki)
    return signal.freqs(num, den, worN=omega)[1]


def noisy(g: np.ndarray, level: float, seed: int) -> np.ndarray:
    """Relative complex noise: G (1 + level (e_r + j e_i)/√2), e ~ N(0, 1)."""
    rng = np.random.default_rng(seed)
    return g * (1 + level * (rng.standard_normal(g.size) + 1j * rng.standard_normal(g.size)) / np.sqrt(2))


def frequency_data(p: dict, kp: float, ki: float, omega=OMEGA, level=0.02, seed=0, name="data") -> dict:
    g = noisy(response(p, kp, ki, omega), level, seed)
    return {"name": name, "omega": list(map(float, omega)), "real": g.real.tolist(), "imag": g.imag.tolist(),
            "constants": {"Kp": kp, "Ki": ki}}


def seed001_model(guess: dict, fixed: tuple[str, ...] = (), margin: float = 0.01) -> dict:
    params = []
    for n in NAMES:
        params.append({"name": n, "value": guess[n], "lower": 0.0, "upper": 20 * guess[n], "fixed": n in fixed})
    return {"kind": "transfer_function", "name": "seed001", "parameters": params,
            "constants": {"Kp": 1.0, "Ki": 1.0},
            "numerator": ["b1", "0", "b2"], "denominator": ["1", "a1", "a2", "a3", "0"],
            "constraints": [f"a1*a2 - a3 >= {margin}"],
            "feedback": {"controller": {"num": ["Kp", "Ki"], "den": ["1", "0"]}}}


def sine_records(p: dict, kp: float, ki: float, omegas, noise: float, seed: int, periods: int = 4,
                 per_period: int = 100) -> list[dict]:
    """One record per frequency: unit sine from rest at t = 0, recorded after the transient.

    The state at the start of the record is computed exactly (steady state plus the decayed free
    response through the matrix exponential), then scipy's lsim simulates the record itself (lsim
    takes the input linear between samples: 100 samples per period keep that error below 0.05 %).
    """
    num, den = closed_loop(p, kp, ki)
    a, b, c, d = signal.tf2ss(num, den)
    slowest = -np.max(np.linalg.eigvals(a).real)
    settle = 25.0 / slowest
    rng = np.random.default_rng(seed)
    records = []
    for w in omegas:
        period = 2 * np.pi / w
        t0 = settle - period                      # one period of (almost decayed) transient kept
        xss = np.linalg.solve(1j * w * np.eye(a.shape[0]) - a, b[:, 0])   # u = Im(e^{jωt})
        x_ss0 = np.imag(xss)                       # steady-state x at t = 0
        x_t0 = np.imag(xss * np.exp(1j * w * t0)) + linalg.expm(a * t0) @ (-x_ss0)
        t = t0 + np.arange(periods * per_period + 1) * period / per_period
        u = np.sin(w * t)
        _, y, _ = signal.lsim((a, b, c, d), u, t - t0, X0=x_t0)
        y = y + noise * np.std(y) * rng.standard_normal(y.size)
        records.append({"omega": float(w), "time": t.tolist(), "input": u.tolist(), "output": y.tolist(),
                        "settle_time": float(settle)})
    return records
