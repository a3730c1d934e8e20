"""Truth systems for the discovery library's physical laws, simulated with scipy (independently of
greyfit), measured in their outputs only, with coloured (AR(1)) or white noise and inputs held
between samples (zero-order hold). Each record function takes a seed; a second seed gives a
validation record."""
from __future__ import annotations

import numpy as np
from scipy.integrate import solve_ivp
from scipy.signal import lfilter


def ar1_noise(n: int, rng: np.random.Generator, rho: float) -> np.ndarray:
    """Unit-variance AR(1) noise (rho = 0: white), stationary from the first sample."""
    e = rng.standard_normal(n + 200)
    out = lfilter([1.0], [1, -rho], e)[200:] if rho else e[200:]
    return out / np.std(out)


def held_levels(n: int, hold: int, lo: float, hi: float, rng: np.random.Generator) -> np.ndarray:
    """A digital controller's output: random levels held for `hold` samples."""
    levels = rng.uniform(lo, hi, n // hold + 1)
    return np.repeat(levels, hold)[:n]


def simulate_held(rhs, t: np.ndarray, x0, u: np.ndarray) -> np.ndarray:
    """States at the samples with the input (n, nu) held over each interval: integrated block by block
    between the samples where the input changes, so no step straddles a jump."""
    u = u.reshape(t.size, -1)
    x = np.empty((len(x0), t.size))
    x[:, 0] = x0
    change = np.flatnonzero(np.any(np.diff(u, axis=0) != 0, axis=1)) + 1
    edges = np.unique(np.concatenate([[0], change, [t.size - 1]]))
    for a, b in zip(edges[:-1], edges[1:]):
        sol = solve_ivp(lambda tt, s, ua=u[a]: rhs(tt, s, ua), (t[a], t[b]), x[:, a], t_eval=t[a:b + 1],
                        method="DOP853", rtol=1e-10, atol=1e-10)
        x[:, a:b + 1] = sol.y
    return x


def _noisy(y: np.ndarray, level: float, rng: np.random.Generator, rho: float) -> list[float]:
    return (y + level * np.std(y) * ar1_noise(y.size, rng, rho)).tolist()


# --- a heated block losing heat by convection and radiation, one thermocouple ---------------------
BLOCK = {"C": 500.0, "h": 2.0, "s": 2.5e-9, "Ta": 293.0}


def block_record(seed: int, n: int = 2000, dt: float = 2.0, noise: float = 0.01, rho: float = 0.5,
                 radiation: bool = True, name: str = "est") -> dict:
    """C dT/dt = P − h (T − Ta) − s (T⁴ − Ta⁴); P held for 100 s at random levels in 0-600 W."""
    rng = np.random.default_rng(300 + seed)
    t = np.arange(n) * dt
    p = held_levels(n, 50, 0.0, 600.0, rng)
    b = BLOCK
    s = b["s"] if radiation else 0.0

    def rhs(tt, x, u):
        return [(u[0] - b["h"] * (x[0] - b["Ta"]) - s * (x[0] ** 4 - b["Ta"] ** 4)) / b["C"]]
    temp = simulate_held(rhs, t, [b["Ta"] + 50.0], p)[0]
    return {"name": name, "time": t.tolist(), "inputs": {"P": p.tolist()},
            "outputs": {"T": _noisy(temp, noise, rng, rho)}}


def block_model(radiation: bool = False) -> dict:
    """Declared with convection only (radiation=False), or complete."""
    params = [{"name": "C", "value": 300.0, "lower": 1.0}, {"name": "h", "value": 1.0, "lower": 0.0}]
    rhs = "(P - h*(T - Ta))/C"
    if radiation:
        params.append({"name": "s", "value": 1e-9, "lower": 0.0})
        rhs = "(P - h*(T - Ta) - s*(T^4 - Ta^4))/C"
    return {"name": "block", "states": ["T"], "inputs": ["P"], "constants": {"Ta": BLOCK["Ta"]},
            "parameters": params, "equations": {"T": rhs}, "outputs": {"T": "T"}}


# --- an oscillator whose damping grows with the amplitude: (c + μ x²) ẋ, position measured -------
VDP = {"m": 1.0, "c": 0.3, "k": 4.0, "mu": 2.0}


def amplitude_damping_record(seed: int, n: int = 1500, dt: float = 0.05, noise: float = 0.01, rho: float = 0.0,
                             name: str = "est") -> dict:
    rng = np.random.default_rng(400 + seed)
    t = np.arange(n) * dt
    u = held_levels(n, 20, -6.0, 6.0, rng)
    v = VDP

    def rhs(tt, x, uu):
        return [x[1], (uu[0] - (v["c"] + v["mu"] * x[0] ** 2) * x[1] - v["k"] * x[0]) / v["m"]]
    x = simulate_held(rhs, t, [0.0, 0.0], u)[0]
    return {"name": name, "time": t.tolist(), "inputs": {"u": u.tolist()}, "outputs": {"y": _noisy(x, noise, rng, rho)}}


def amplitude_damping_model() -> dict:
    return {"name": "oscillator", "states": ["y", "yd"], "inputs": ["u"],
            "parameters": [{"name": "m", "value": 1.0, "fixed": True}, {"name": "c", "value": 1.0, "lower": 0.0},
                           {"name": "k", "value": 2.0, "lower": 0.0}],
            "equations": {"y": "yd", "yd": "(u - c*yd - k*y)/m"}, "outputs": {"y": "y"}}


# --- a stirred reactor whose rate constant follows Arrhenius, declared constant --------------------
REACTOR = {"q": 0.005, "cin": 1.0, "k": 0.01, "E": 6000.0, "Tref": 330.0, "h": 0.02, "Ta": 300.0, "Cp": 1.0}


def reactor_record(seed: int, n: int = 2000, dt: float = 5.0, noise: float = 0.01, rho: float = 0.5,
                   name: str = "est") -> dict:
    """dc/dt = q (cin − c) − k(T) c, k(T) = k exp(−E (1/T − 1/Tref)); dT/dt = (P − h (T − Ta))/Cp,
    the heater P held for 250 s; concentration and temperature measured."""
    rng = np.random.default_rng(500 + seed)
    t = np.arange(n) * dt
    p = held_levels(n, 50, 0.0, 1.4, rng)
    r = REACTOR

    def rhs(tt, x, u):
        rate = r["k"] * np.exp(-r["E"] * (1 / x[1] - 1 / r["Tref"]))
        return [r["q"] * (r["cin"] - x[0]) - rate * x[0], (u[0] - r["h"] * (x[1] - r["Ta"])) / r["Cp"]]
    x = simulate_held(rhs, t, [0.5, 320.0], p)
    return {"name": name, "time": t.tolist(), "inputs": {"P": p.tolist()},
            "outputs": {"c": _noisy(x[0], noise, rng, rho), "T": _noisy(x[1], noise, rng, rho)}}


def reactor_model() -> dict:
    return {"name": "reactor", "states": ["c", "T"], "inputs": ["P"],
            "constants": {"q": REACTOR["q"], "cin": REACTOR["cin"], "Ta": REACTOR["Ta"], "Cp": REACTOR["Cp"]},
            "parameters": [{"name": "k", "value": 0.02, "lower": 0.0}, {"name": "h", "value": 0.01, "lower": 0.0}],
            "equations": {"c": "q*(cin - c) - k*c", "T": "(P - h*(T - Ta))/Cp"}, "outputs": {"c": "c", "T": "T"}}


# --- a series RLC with a load across the capacitor; the capacitor's voltage sensor has an offset ---
RLC = {"L": 0.5, "R": 2.0, "C": 0.1, "Rl": 20.0, "bias": 0.3}


def rlc_record(seed: int, n: int = 2000, dt: float = 0.01, noise: float = 0.01, rho: float = 0.5,
               name: str = "est") -> dict:
    """L di/dt = u − R i − vc, C dvc/dt = i − vc/Rl; measured: i, and vc + bias."""
    rng = np.random.default_rng(600 + seed)
    t = np.arange(n) * dt
    u = held_levels(n, 40, -5.0, 10.0, rng)
    c = RLC

    def rhs(tt, x, uu):
        return [(uu[0] - c["R"] * x[0] - x[1]) / c["L"], (x[0] - x[1] / c["Rl"]) / c["C"]]
    x = simulate_held(rhs, t, [0.0, 0.0], u)
    return {"name": name, "time": t.tolist(), "inputs": {"u": u.tolist()},
            "outputs": {"i": _noisy(x[0], noise, rng, rho), "vc": _noisy(x[1] + c["bias"], noise, rng, rho)}}


def rlc_model() -> dict:
    return {"name": "rlc", "states": ["i", "vc"], "inputs": ["u"], "constants": {"Rl": RLC["Rl"]},
            "parameters": [{"name": "L", "value": 0.3, "lower": 1e-3}, {"name": "R", "value": 1.0, "lower": 0.0},
                           {"name": "C", "value": 0.2, "lower": 1e-3}],
            "equations": {"i": "(u - R*i - vc)/L", "vc": "(i - vc/Rl)/C"}, "outputs": {"i": "i", "vc": "vc"}}


def amplitude_damping_complete_model() -> dict:
    model = amplitude_damping_model()
    model["parameters"].append({"name": "mu", "value": 1.0, "lower": 0.0})
    model["equations"]["yd"] = "(u - (c + mu*y^2)*yd - k*y)/m"
    return model


def rlc_complete_model() -> dict:
    model = rlc_model()
    model["parameters"].append({"name": "bias", "value": 0.0})
    model["outputs"] = {"i": "i", "vc": "vc + bias"}
    return model


# complete models (nothing missing) under AR(1) noise (ρ 0.8) and held inputs, 500 samples: the loop
# must add nothing (tests/solvers/test_discovery_library.py on two seeds,
# bench/bench_discovery_noise.py --library over many)
COMPLETE = {
    "block": (block_model(radiation=True), lambda seed: block_record(seed, n=500, rho=0.8)),
    "oscillator": (amplitude_damping_complete_model(),
                   lambda seed: amplitude_damping_record(seed, n=500, rho=0.8)),
    "rlc": (rlc_complete_model(), lambda seed: rlc_record(seed, n=500, rho=0.8)),
}
