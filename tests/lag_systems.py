"""Linear truth systems with unmodelled first-order dynamics, simulated exactly (matrix exponential of
the held input, independent of greyfit): a sensor lag on the output, an actuator lag on the input,
or an extra pole between two states. The declared models lack the lag.

Systems: an RL circuit measured by its current, a mass-spring-damper measured by its position, and a
two-node thermal chain (heater -> node 1 -> node 2, both measured) whose coupling passes through a
wall the model lacks.
"""
from __future__ import annotations

import numpy as np
from scipy.linalg import expm

SYSTEMS = {
    # name: (A, B, C, dt, declared model)
    "rl": (np.array([[-100.0]]), np.array([[100.0]]), np.array([[1.0]]), 1e-3, {
        "states": ["i"], "inputs": ["u"],
        "parameters": [{"name": "R", "value": 0.5, "lower": 0}, {"name": "L", "value": 0.02, "lower": 0}],
        "equations": {"i": "(u - R*i)/L"}, "outputs": {"i": "i"}}),
    "msd": (np.array([[0.0, 1.0], [-5.0 / 2.0, -0.8 / 2.0]]), np.array([[0.0], [1.0 / 2.0]]),
            np.array([[1.0, 0.0]]), 0.02, {
                "states": ["x", "v"], "inputs": ["u"],
                "parameters": [{"name": "m", "value": 1.5, "lower": 0}, {"name": "c", "value": 0.5, "lower": 0},
                               {"name": "k", "value": 4.0, "lower": 0}],
                "equations": {"x": "v", "v": "(u - c*v - k*x)/m"}, "outputs": {"x": "x"}}),
    "thermal": (np.array([[-0.2, 0.0], [0.5, -0.6]]), np.array([[0.1], [0.0]]), np.eye(2), 0.1, {
        "states": ["T1", "T2"], "inputs": ["P"],
        "parameters": [{"name": "g1", "value": 0.15, "lower": 0}, {"name": "b", "value": 0.08, "lower": 0},
                       {"name": "g12", "value": 0.4, "lower": 0}, {"name": "g2", "value": 0.5, "lower": 0}],
        "equations": {"T1": "b*P - g1*T1", "T2": "g12*T1 - g2*T2"}, "outputs": {"T1": "T1", "T2": "T2"}}),
}
TRUTH = {"rl": {"R": 1.0, "L": 0.01}, "msd": {"m": 2.0, "c": 0.8, "k": 5.0},
         "thermal": {"g1": 0.2, "b": 0.1, "g12": 0.5, "g2": 0.6}}


def augmented(A, B, C, lag: str, tau: float, pair: tuple[int, int] = (1, 0)):
    """(A, B, C) with a first-order lag of time constant `tau`: 'sensor' on the first output, 'input' on the
    input, 'pole' where state pair[1] enters the equation of state pair[0]; 'none' unchanged."""
    n = A.shape[0]
    if lag == "none" or tau <= 0:
        return A, B, C
    a = np.zeros((n + 1, n + 1))
    a[:n, :n] = A
    b = np.zeros((n + 1, B.shape[1]))
    c = np.zeros((C.shape[0], n + 1))
    if lag == "sensor":
        a[n, :n] = C[0] / tau
        a[n, n] = -1 / tau
        b[:n] = B
        c[1:, :n] = C[1:]
        c[0, n] = 1.0
    elif lag == "input":
        a[:n, n] = B[:, 0]
        a[n, n] = -1 / tau
        b[n, 0] = 1 / tau
        c[:, :n] = C
    else:
        i, j = pair
        a[i, j] = 0.0
        a[i, n] = A[i, j]
        a[n, j] = 1 / tau
        a[n, n] = -1 / tau
        b[:n] = B
        c[:, :n] = C
    return a, b, c


def held_input(seed: int, n: int, hold: int = 10, amplitude: float = 5.0) -> np.ndarray:
    """A random binary input held for `hold` samples."""
    rng = np.random.default_rng(seed)
    return np.repeat(rng.choice([-amplitude, amplitude], size=n // hold + 1), hold)[:n]


def simulate(A, B, C, u: np.ndarray, dt: float) -> np.ndarray:
    """y at the samples for an input held between them, from rest (exact: the matrix exponential)."""
    n = A.shape[0]
    block = np.zeros((n + 1, n + 1))
    block[:n, :n], block[:n, n:] = A * dt, B * dt
    phi = expm(block)
    ad, bd = phi[:n, :n], phi[:n, n:]
    x = np.zeros(n)
    y = np.empty((C.shape[0], u.size))
    for k in range(u.size):
        y[:, k] = C @ x
        x = ad @ x + bd[:, 0] * u[k]
    return y


def lag_record(system: str, lag: str, tau_samples: float, seed: int, n: int = 400,
               noise: float = 0.01, name: str = "est") -> dict:
    """A record of `system` with the lag (time constant in samples), noise `noise` × the output's spread."""
    A, B, C, dt, model = SYSTEMS[system]
    u = held_input(seed, n)
    y = simulate(*augmented(A, B, C, lag, tau_samples * dt), u, dt)
    rng = np.random.default_rng(seed + 1000)
    y = y + noise * np.std(y, axis=1, keepdims=True) * rng.standard_normal(y.shape)
    return {"name": name, "time": (np.arange(n) * dt).tolist(), "inputs": {model["inputs"][0]: u.tolist()},
            "outputs": {out: row.tolist() for out, row in zip(model["outputs"], y)}}


def declared(system: str) -> dict:
    """The declared model (without the lag)."""
    return SYSTEMS[system][4]
