"""Write the tutorial's fit request: an RC circuit driven by a held square-wave voltage.

    C dv/dt = (u - v) / R        measured: the capacitor voltage v and the current i = (u - v) / R

R = 1 kΩ and C = 1 mF (time constant 1 s), sampled every 20 ms for 20 s; the first 10 s are fitted
and the last 10 s kept apart as a validation record. Noise: 5 mV on v, 5 µA on i.
Usage: python docs/tutorial/make_rc_request.py > rc.json
"""
import json

import numpy as np

R, C, DT = 1000.0, 1e-3, 0.02


def held_input(n: int, rng: np.random.Generator) -> np.ndarray:
    """A square wave whose half-periods (0.4-2 s) are drawn at random, held between samples."""
    u, level, k = np.zeros(n), 5.0, 0
    while k < n:
        width = int(rng.integers(20, 100))
        u[k:k + width] = level
        level, k = 5.0 - level, k + width
    return u


def simulate(u: np.ndarray) -> np.ndarray:
    """Exact discretisation of the RC circuit under a held input (zero-order hold)."""
    a = np.exp(-DT / (R * C))
    v = np.zeros_like(u)
    for k in range(len(u) - 1):
        v[k + 1] = a * v[k] + (1 - a) * u[k]
    return v


def record(name: str, t, u, v, rng) -> dict:
    i = (u - v) / R
    return {"name": name, "time": t.round(6).tolist(), "inputs": {"u": u.tolist()},
            "outputs": {"v": (v + 0.005 * rng.standard_normal(len(t))).round(6).tolist(),
                        "i": (i + 5e-6 * rng.standard_normal(len(t))).round(9).tolist()}}


def main() -> None:
    rng = np.random.default_rng(7)
    t = np.arange(1001) * DT
    u = held_input(len(t), rng)
    v = simulate(u)
    request = {
        "model": {
            "name": "rc",
            "states": ["v"],
            "inputs": ["u"],
            "parameters": [{"name": "R", "value": 300.0, "lower": 1.0, "unit": "ohm"},
                           {"name": "C", "value": 3e-3, "lower": 1e-6, "unit": "F"}],
            "equations": {"v": "(u - v)/(R*C)"},
            "outputs": {"v": "v", "i": "(u - v)/R"},
        },
        "experiments": [record("estimation", t[:501], u[:501], v[:501], rng)],
        "validation": [record("validation", t[500:], u[500:], v[500:], rng)],
        "method": "multiple_shooting",
        "options": {"input_interpolation": "zoh"},
    }
    print(json.dumps(request))


if __name__ == "__main__":
    main()
