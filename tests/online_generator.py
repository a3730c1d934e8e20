"""Random systems for the online estimators (RLS, MRAS), simulated exactly without greyfit.

Continuous-time, linear, every state measured (MRAS's reference is the measured state), 1 ms
sampling, the input held between samples (a digital controller's zero-order hold), measurement
noise of 0.1-1 % of each state's spread:

  rl      L di/dt = u − R i                              R, L
  first   dy/dt = −a y + b u                              a, b
  rlc     L di/dt = u − R i − v,  C dv/dt = i             R, L, C
  second  dx/dt = v,  m dv/dt = u − c v − k x             k, c, m

Inputs: `rich` (a held PRBS plus three sines of random frequencies), `dc` (a constant), `one_sine`
(persistently exciting of order 2), `two_sines` (order 4). Equation error's regression of the
second-order plants has three coefficients in one equation and needs order 3; the first-order ones 2.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tests.lag_systems import simulate

DT = 1e-3
SYSTEMS = ("rl", "first", "rlc", "second")
INPUTS = ("rich", "dc", "one_sine", "two_sines")
NEEDED_ORDER = {"rl": 2, "first": 2, "rlc": 3, "second": 3}


@dataclass
class OnlineCase:
    body: dict      # a FitRequest without its method
    truth: dict     # the true parameters


def _truth(system: str, rng) -> tuple[dict, np.ndarray, np.ndarray]:
    """(parameters, A, B) of a random plant with its modes between 2 and 40 rad/s."""
    if system == "rl":
        p = {"R": rng.uniform(1, 5), "L": 0.0}
        p["L"] = p["R"] / rng.uniform(5, 40)
        return p, np.array([[-p["R"] / p["L"]]]), np.array([[1 / p["L"]]])
    if system == "first":
        p = {"a": rng.uniform(5, 40), "b": rng.uniform(5, 50)}
        return p, np.array([[-p["a"]]]), np.array([[p["b"]]])
    wn, zeta = rng.uniform(5, 30), rng.uniform(0.2, 0.8)
    if system == "rlc":
        L = rng.uniform(0.1, 1.0)
        p = {"R": 2 * zeta * wn * L, "L": L, "C": 1 / (wn ** 2 * L)}
        return p, np.array([[-p["R"] / L, -1 / L], [1 / p["C"], 0.0]]), np.array([[1 / L], [0.0]])
    m = rng.uniform(0.5, 5)
    p = {"k": wn ** 2 * m, "c": 2 * zeta * wn * m, "m": m}
    return p, np.array([[0.0, 1.0], [-p["k"] / m, -p["c"] / m]]), np.array([[0.0], [1 / m]])


MODELS = {
    "rl": (["i"], {"i": "(u - R*i)/L"}),
    "first": (["y"], {"y": "-a*y + b*u"}),
    "rlc": (["i", "v"], {"i": "(u - R*i - v)/L", "v": "i/C"}),
    "second": (["x", "v"], {"x": "v", "v": "(u - c*v - k*x)/m"}),
}


def _input(kind: str, t: np.ndarray, rng) -> np.ndarray:
    f = rng.uniform(0.5, 5.0, size=3) * np.array([1.0, 2.3, 5.1])
    if kind == "dc":
        return np.full(t.size, rng.uniform(0.5, 2.0))
    if kind == "one_sine":
        return np.sin(2 * np.pi * f[0] * t)
    if kind == "two_sines":
        return np.sin(2 * np.pi * f[0] * t) + np.sin(2 * np.pi * f[1] * t)
    hold = int(rng.integers(10, 50))
    prbs = np.repeat(rng.choice([-1.0, 1.0], size=t.size // hold + 1), hold)[:t.size]
    return prbs + sum(np.sin(2 * np.pi * fk * t + rng.uniform(0, 2 * np.pi)) for fk in f)


def random_case(system: str, inputs: str, seed: int, duration: float = 4.0) -> OnlineCase:
    """One random plant of `system` driven by `inputs`, with its record and its declared model."""
    rng = np.random.default_rng(seed)
    truth, a, b = _truth(system, rng)
    t = np.arange(int(round(duration / DT)) + 1) * DT
    u = _input(inputs, t, rng)
    x = simulate(a, b, np.eye(a.shape[0]), u, DT)
    x = x + rng.uniform(0.001, 0.01) * np.std(x, axis=1, keepdims=True) * rng.standard_normal(x.shape)
    states, equations = MODELS[system]
    params = [{"name": n, "value": v * float(rng.uniform(0.6, 1.6)), "lower": 0.0} for n, v in truth.items()]
    model = {"states": states, "inputs": ["u"], "parameters": params, "equations": equations}
    exp = {"name": "run", "time": t.tolist(), "inputs": {"u": u.tolist()},
           "outputs": {s: row.tolist() for s, row in zip(states, x)}}
    options = {"input_interpolation": "zoh", "rls": {"trajectory_every": 50}, "mras": {"trajectory_every": 50}}
    return OnlineCase({"model": model, "experiments": [exp], "options": options}, truth)
