"""Truth systems for the shape step and the loop's solid ground, simulated with scipy independently
of greyfit, measured in outputs only; noise white or AR(1), inputs linear or held between samples.

- a Bouc-Wen hysteretic isolator (a restoring force with memory: no function of the present state
  explains it), declared as a linear mass-spring-damper;
- a two-lag process with a transport delay, sampled coarsely (1 s) under a held input;
- a stiff Duffing oscillator (k = 30) measured in position;
- a heated block with radiative loss s(T⁴ − Ta⁴), declared with convection only (one thermocouple).
"""
from __future__ import annotations

import numpy as np
from scipy.integrate import solve_ivp
from scipy.signal import lfilter

from tests.partial_systems import multisine


def noise(n: int, kind: str, seed: int, rho: float = 0.8) -> np.ndarray:
    """Unit-variance white or AR(1) noise (stationary from the first sample)."""
    e = np.random.default_rng(seed).standard_normal(n + 300)
    out = e if kind == "white" else lfilter([1.0], [1.0, -rho], e)
    out = out[300:]
    return out / np.std(out)


def _held(rhs, t, x0, u):
    """States with u held over each interval (each interval integrated on its own)."""
    x = np.empty((len(x0), t.size))
    x[:, 0] = x0
    for k in range(t.size - 1):
        sol = solve_ivp(lambda tt, s, uk=u[k]: rhs(s, uk), (t[k], t[k + 1]), x[:, k], method="DOP853",
                        rtol=1e-10, atol=1e-12)
        x[:, k + 1] = sol.y[:, -1]
    return x


def _linear(rhs, t, x0, u):
    """States with u linear between samples (as greyfit's first-order hold)."""
    dt = t[1] - t[0]

    def u_of(tt):
        k = min(max(int(tt / dt), 0), u.size - 2)
        a = tt / dt - k
        return u[k] + a * (u[k + 1] - u[k])
    sol = solve_ivp(lambda tt, s: rhs(s, u_of(tt)), (t[0], t[-1]), x0, t_eval=t, method="DOP853",
                    rtol=1e-10, atol=1e-12, max_step=dt / 2)
    return sol.y


def _record(t, u, y, level, kind, seed, name, output="y"):
    yn = y + level * np.std(y) * noise(t.size, kind, seed)
    return {"name": name, "time": t.tolist(), "inputs": {"u": u.tolist()}, "outputs": {output: yn.tolist()}}


# --- Bouc-Wen isolator: m x'' + c x' + a k x + (1 - a) k z = u, ż = ẋ - β|ẋ| z - γ ẋ |z| ------------
BOUC_WEN = {"m": 1.0, "c": 0.3, "k": 4.0, "a": 0.2, "beta": 0.6, "gamma": 0.4}


def bouc_wen_record(seed: int, n: int = 2000, dt: float = 0.05, level: float = 0.01, kind: str = "white",
                    name: str = "est") -> dict:
    p = BOUC_WEN
    t = np.arange(n) * dt
    u = 3.0 * multisine(t, [0.04, 0.09, 0.17, 0.26, 0.38], [1.0, 0.9, 0.7, 0.5, 0.4], seed)

    def rhs(s, uu):
        x, v, z = s
        zd = v - p["beta"] * abs(v) * z - p["gamma"] * v * abs(z)
        return [v, (uu - p["c"] * v - p["a"] * p["k"] * x - (1 - p["a"]) * p["k"] * z) / p["m"], zd]
    x = _linear(rhs, t, [0.0, 0.0, 0.0], u)
    return _record(t, u, x[0], level, kind, 500 + seed, name)


def bouc_wen_model() -> dict:
    return {"name": "isolator", "states": ["x", "v"], "inputs": ["u"],
            "parameters": [{"name": "m", "value": 1.0, "fixed": True},
                           {"name": "c", "value": 0.5, "lower": 0.0}, {"name": "k", "value": 2.0, "lower": 0.0}],
            "equations": {"x": "v", "v": "(u - c*v - k*x)/m"}, "outputs": {"y": "x"}}


# --- two lags in series with a transport delay, 1 s sample, held input ----------------------------
DELAY = {"K": 2.0, "tau1": 15.0, "tau2": 4.0, "delay_samples": 4}


def delay_input(n: int, seed: int) -> np.ndarray:
    """A held random staircase: a new level every 10-40 samples (a plant test by hand)."""
    rng = np.random.default_rng(seed)
    u = np.empty(n)
    k = 0
    while k < n:
        length = int(rng.integers(10, 40))
        u[k:k + length] = rng.uniform(-1.0, 1.0)
        k += length
    return u


def delay_record(seed: int, n: int = 2000, level: float = 0.01, kind: str = "white", name: str = "est") -> dict:
    p = DELAY
    t = np.arange(n) * 1.0
    u = delay_input(n, seed)
    lag = p["delay_samples"]
    u_late = np.concatenate([np.zeros(lag), u[:-lag]])

    def rhs(s, uu):
        return [(p["K"] * uu - s[0]) / p["tau1"], (s[0] - s[1]) / p["tau2"]]
    x = _held(rhs, t, [0.0, 0.0], u_late)
    return _record(t, u, x[1], level, kind, 600 + seed, name)


def delay_model() -> dict:
    """The two lags declared without the delay; started 30 % off."""
    return {"name": "two_lags", "states": ["x1", "x2"], "inputs": ["u"],
            "parameters": [{"name": "K", "value": 1.5}, {"name": "tau1", "value": 10.0, "lower": 0.01},
                           {"name": "tau2", "value": 3.0, "lower": 0.01}],
            "equations": {"x1": "(K*u - x1)/tau1", "x2": "(x1 - x2)/tau2"}, "outputs": {"y": "x2"}}


# --- a stiff Duffing oscillator: m y'' + d y' + k y + k3 y³ = u, position measured --------------------
STIFF_DUFFING = {"m": 1.0, "d": 0.8, "k": 30.0, "k3": 20.0}


def stiff_duffing_record(seed: int, n: int = 2000, dt: float = 0.02, level: float = 0.01, kind: str = "white",
                         name: str = "est", amplitude: float = 20.0, freqs=(0.1, 0.25, 0.45, 0.7, 1.1),
                         **truth) -> dict:
    p = {**STIFF_DUFFING, **truth}
    t = np.arange(n) * dt
    u = amplitude * multisine(t, list(freqs), [1.0, 0.9, 0.8, 0.6, 0.5][:len(freqs)], seed)

    def rhs(s, uu):
        return [s[1], (uu - p["d"] * s[1] - p["k"] * s[0] - p["k3"] * s[0] ** 3) / p["m"]]
    x = _linear(rhs, t, [0.0, 0.0], u)
    return _record(t, u, x[0], level, kind, 700 + seed, name)


def stiff_duffing_model(k: float = 10.0) -> dict:
    return {"name": "duffing", "states": ["y", "yd"], "inputs": ["u"],
            "parameters": [{"name": "m", "value": 1.0, "fixed": True},
                           {"name": "d", "value": 1.0, "lower": 0.0}, {"name": "k", "value": k, "lower": 0.0}],
            "equations": {"y": "yd", "yd": "(u - d*yd - k*y)/m"}, "outputs": {"y": "y"}}


# --- a heated block losing heat by convection and radiation, one thermocouple ----------------------
THERMAL = {"C": 500.0, "h": 0.5, "s": 2.55e-9, "Ta": 293.0}   # J/K, W/K, W/K⁴ (ε σ A), K


def heater_power(n: int, seed: int) -> np.ndarray:
    """Held heater steps between 0 and 200 W, a new level every 60-200 samples."""
    rng = np.random.default_rng(seed)
    p = np.empty(n)
    k = 0
    while k < n:
        length = int(rng.integers(60, 200))
        p[k:k + length] = rng.uniform(0.0, 200.0)
        k += length
    return p


def thermal_record(seed: int, n: int = 2000, dt: float = 5.0, level: float = 0.005, kind: str = "white",
                   name: str = "est") -> dict:
    p = THERMAL
    t = np.arange(n) * dt
    power = heater_power(n, seed)

    def rhs(s, q):
        temp = s[0]
        return [(q - p["h"] * (temp - p["Ta"]) - p["s"] * (temp ** 4 - p["Ta"] ** 4)) / p["C"]]
    x = _held(rhs, t, [p["Ta"]], power)
    rec = _record(t, power, x[0], level, kind, 800 + seed, name, output="T_meas")
    rec["inputs"] = {"P": rec["inputs"].pop("u")}
    return rec


def thermal_model() -> dict:
    """Convection only declared; the block starts at the ambient temperature."""
    return {"name": "heated_block", "states": ["T"], "inputs": ["P"], "constants": {"Ta": THERMAL["Ta"]},
            "parameters": [{"name": "C", "value": 300.0, "lower": 1.0}, {"name": "h", "value": 1.0, "lower": 0.0}],
            "equations": {"T": "(P - h*(T - Ta))/C"}, "outputs": {"T_meas": "T"}}
