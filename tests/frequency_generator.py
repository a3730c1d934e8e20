"""Random frequency-fit systems with random unmodelled dynamics, simulated with scipy only.

A plant of order 2 or 3 (a lightly or well damped pair, a real pole, a left-half-plane zero half of
the time), written as a transfer function of its coefficients b/a (monic denominator), measured at
30-60 log-spaced frequencies around its poles with relative complex noise of 0.5-3 %. The truth may
have one more factor the declared model lacks:

  right          none
  missing_pole   p/(s + p), p from a tenth to ten times the highest measured frequency
  missing_zero   (1 + s/z), z likewise
  delay          e^(−sT), 3-30° of phase at the highest frequency
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import signal

KINDS = ("right", "missing_pole", "missing_zero", "delay")


@dataclass
class FrequencyCase:
    body: dict            # the FrequencyFitRequest
    truth: dict           # the declared parameters' true values
    extra: str            # the factor the model lacks, for the report


def _plant(rng) -> tuple[np.ndarray, np.ndarray, float]:
    wn = 10 ** rng.uniform(0, 2)
    zeta = rng.uniform(0.1, 0.9)
    den = np.array([1.0, 2 * zeta * wn, wn ** 2])
    if rng.random() < 0.5:
        den = np.polymul(den, [1.0, wn * 10 ** rng.uniform(-0.7, 0.7)])
    gain = rng.uniform(0.5, 5.0)
    num = np.array([gain * den[-1]])
    if rng.random() < 0.5:
        z = wn * 10 ** rng.uniform(-0.5, 1.0)
        num = gain * den[-1] * np.array([1.0 / z, 1.0])
    return num, den, wn


def _model(num: np.ndarray, den: np.ndarray, rng) -> tuple[dict, dict]:
    names_b = [f"b{k}" for k in range(num.size - 1, -1, -1)]
    names_a = [f"a{k}" for k in range(den.size - 2, -1, -1)]
    truth = dict(zip(names_b, num.tolist())) | dict(zip(names_a, den[1:].tolist()))
    params = [{"name": n, "value": v * float(rng.uniform(0.7, 1.4)), "lower": 0.0, "upper": 50.0 * v}
              for n, v in truth.items()]
    return {"kind": "transfer_function", "name": "plant", "parameters": params,
            "numerator": names_b, "denominator": ["1", *names_a]}, truth


def random_case(seed: int, kind: str) -> FrequencyCase:
    """One random system with the misspecification `kind` (`KINDS`), its data and declared model."""
    rng = np.random.default_rng(seed)
    num, den, wn = _plant(rng)
    w_lo, w_hi = wn / 10 ** rng.uniform(0.7, 1.3), wn * 10 ** rng.uniform(0.5, 1.5)
    omega = np.logspace(np.log10(w_lo), np.log10(w_hi), int(rng.integers(30, 61)))
    g = signal.freqs(num, den, worN=omega)[1]
    extra = "none"
    if kind == "missing_pole":
        p = w_hi * 10 ** rng.uniform(-1, 1)
        g, extra = g * p / (1j * omega + p), f"pole at {p:.3g} rad/s"
    elif kind == "missing_zero":
        z = w_hi * 10 ** rng.uniform(-1, 1)
        g, extra = g * (1 + 1j * omega / z), f"zero at {z:.3g} rad/s"
    elif kind == "delay":
        delay = np.deg2rad(rng.uniform(3, 30)) / w_hi
        g, extra = g * np.exp(-1j * omega * delay), f"delay {delay:.3g} s"
    level = rng.uniform(0.005, 0.03)
    g = g * (1 + level * (rng.standard_normal(g.size) + 1j * rng.standard_normal(g.size)) / np.sqrt(2))
    model, truth = _model(num, den, rng)
    data = {"name": "data", "omega": omega.tolist(), "real": g.real.tolist(), "imag": g.imag.tolist()}
    return FrequencyCase({"model": model, "data": [data], "options": {"stability": "check"}}, truth, extra)
