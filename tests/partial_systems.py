"""Truth systems measured in their outputs only (positions, one level, |speed|), simulated with scipy
independently of greyfit, each with a second record for validation."""
from __future__ import annotations

import numpy as np
from scipy.integrate import solve_ivp


def multisine(t, freqs, amps, seed):
    rng = np.random.default_rng(seed)
    phases = rng.uniform(0, 2 * np.pi, len(freqs))
    return sum(a * np.sin(2 * np.pi * f * t + p) for f, a, p in zip(freqs, amps, phases))


def _simulate(rhs, t, x0, u_of):
    sol = solve_ivp(lambda tt, x: rhs(tt, x, u_of(tt)), (t[0], t[-1]), x0, t_eval=t, method="DOP853",
                    rtol=1e-10, atol=1e-12, max_step=(t[1] - t[0]) / 2)
    return sol.y


def _noisy(y, level, rng):
    return y + level * np.std(y) * rng.standard_normal(y.size)


# --- Duffing oscillator: m y'' + d y' + k y + k3 y^3 = u, position measured ------------------------
DUFFING_TRUTH = {"m": 1.0, "d": 0.4, "k": 2.0, "k3": 3.0}


def duffing_input(t, seed):
    return multisine(t, [0.05, 0.13, 0.21, 0.34, 0.47], [1.2, 1.0, 0.8, 0.6, 0.5], seed)


def duffing_record(seed: int, noise: float = 0.01, n: int = 1501, dt: float = 0.05, name="e"):
    t = np.arange(n) * dt
    p = DUFFING_TRUTH
    u_s = duffing_input(t, seed)

    def u_of(tt):
        return float(np.interp(tt, t, u_s))
    x = _simulate(lambda tt, s, u: [s[1], (u - p["d"] * s[1] - p["k"] * s[0] - p["k3"] * s[0] ** 3) / p["m"]],
                  t, [0.0, 0.0], u_of)
    rng = np.random.default_rng(100 + seed)
    return {"name": name, "time": t.tolist(), "inputs": {"u": u_s.tolist()},
            "outputs": {"y": _noisy(x[0], noise, rng).tolist()}}


def duffing_model() -> dict:
    return {"name": "duffing", "states": ["y", "yd"], "inputs": ["u"],
            "parameters": [{"name": "m", "value": 1.0, "fixed": True},
                           {"name": "d", "value": 1.0, "lower": 0.0}, {"name": "k", "value": 4.0, "lower": 0.0}],
            "equations": {"y": "yd", "yd": "(u - d*yd - k*y)/m"}, "outputs": {"y": "y"}}


# --- two cascaded tanks, only the lower level measured --------------------------------------------
TANKS_TRUTH = {"a1": 0.5, "a2": 0.4}


def tanks_input(t, seed):
    return 0.3 + multisine(t, [0.004, 0.009, 0.017, 0.03], [0.08, 0.07, 0.05, 0.04], seed)


def tanks_record(seed: int, noise: float = 0.01, n: int = 1001, dt: float = 0.5, name="e"):
    t = np.arange(n) * dt
    u_s = tanks_input(t, seed)
    a1, a2 = TANKS_TRUTH["a1"], TANKS_TRUTH["a2"]

    def u_of(tt):
        return float(np.interp(tt, t, u_s))

    def rhs(tt, h, u):
        q1 = a1 * np.sqrt(max(h[0], 0.0))
        return [u - q1, q1 - a2 * np.sqrt(max(h[1], 0.0))]
    x = _simulate(rhs, t, [0.36, 0.56], u_of)
    rng = np.random.default_rng(200 + seed)
    return {"name": name, "time": t.tolist(), "inputs": {"u": u_s.tolist()},
            "outputs": {"h2m": _noisy(x[1], noise, rng).tolist()}}


def tanks_model() -> dict:
    """Declared with linear outflows, both tanks of unit area; only the lower level is an output."""
    return {"name": "tanks", "states": ["h1", "h2"], "inputs": ["u"],
            "parameters": [{"name": "k1", "value": 0.5, "lower": 0.0}, {"name": "k2", "value": 0.5, "lower": 0.0}],
            "equations": {"h1": "u - k1*h1", "h2": "k1*h1 - k2*h2"}, "outputs": {"h2m": "h2"}}


# --- a speed sensor that cannot see the sign: y = |w| ---------------------------------------------
SPEED_TRUTH = {"b": 0.5, "K": 2.0}


def speed_record(seed: int, noise: float = 0.01, n: int = 1001, dt: float = 0.02, name="e"):
    t = np.arange(n) * dt
    u_s = multisine(t, [0.1, 0.27, 0.55], [1.0, 0.7, 0.5], seed)

    def u_of(tt):
        return float(np.interp(tt, t, u_s))
    x = _simulate(lambda tt, w, u: [-SPEED_TRUTH["b"] * w[0] + SPEED_TRUTH["K"] * u], t, [0.0], u_of)
    rng = np.random.default_rng(300 + seed)
    return {"name": name, "time": t.tolist(), "inputs": {"u": u_s.tolist()},
            "outputs": {"y": (np.abs(x[0]) + noise * np.std(np.abs(x[0])) * rng.standard_normal(n)).tolist()}}


def speed_model() -> dict:
    return {"name": "motor_speed", "states": ["w"], "inputs": ["u"],
            "parameters": [{"name": "b", "value": 1.0, "lower": 0.0}, {"name": "K", "value": 1.0}],
            "equations": {"w": "-b*w + K*u"}, "outputs": {"y": "w"}}
