"""Truth systems of the online-estimation tests (seeds 003 and 004), simulated without greyfit.

RL circuit (seed 003, example 7-5): L di/dt = -R i + u with the voltage held between samples
(a digital controller's zero-order hold), so the exact sampled response is
i[k+1] = exp(-T R/L) i[k] + (1 - exp(-T R/L))/R u[k]; a time-varying R is taken at the middle of
each interval (the change of R within 1 ms is below 1e-4 of its value).
Seed 004: first order 200/(s+100) and second order 20000/(s^2 + 2s + 10000) discretised exactly
(zero-order hold, scipy.signal.cont2discrete), input sin(2π·2t) + 0.1 sin(2π·20t), T = 1 ms,
white measurement noise of power 1e-5.
"""
from __future__ import annotations

import numpy as np
from scipy import signal

RL_TRUTH = {"R": 2.0, "L": 0.5}
RL_T = 1e-3


def rl_input(t: np.ndarray, seed: int = 0) -> np.ndarray:
    """Persistently exciting voltage: three sinusoids plus a pseudo-random binary component."""
    rng = np.random.default_rng(seed)
    prbs = np.repeat(rng.choice([-1.0, 1.0], size=t.size // 20 + 1), 20)[:t.size]
    return 2.0 * np.sin(2 * np.pi * 1.0 * t) + np.sin(2 * np.pi * 7.0 * t) + 0.5 * np.sin(2 * np.pi * 31 * t) + prbs


def simulate_rl(duration: float, r_of_t=None, L: float = RL_TRUTH["L"], noise: float = 0.0, seed: int = 0):
    """(t, u, i) sampled every 1 ms; `r_of_t(t)` makes R time varying (default 2 Ω)."""
    n = int(round(duration / RL_T)) + 1
    t = np.arange(n) * RL_T
    u = rl_input(t, seed)
    r = np.full(n, RL_TRUTH["R"]) if r_of_t is None else r_of_t(t + RL_T / 2)
    a = np.exp(-RL_T * r / L)
    b = (1 - a) / r
    i = np.zeros(n)
    for k in range(n - 1):
        i[k + 1] = a[k] * i[k] + b[k] * u[k]
    rng = np.random.default_rng(seed + 1000)
    return t, u, i + noise * rng.standard_normal(n)


def rl_model(R: float = 1.0, L: float = 1.0) -> dict:
    """Seed 003's discrete RL circuit in its physical parameters: i[k+1] = (1 - T R/L) i + T/L u."""
    return {"name": "rl_circuit", "states": ["i"], "inputs": ["u"], "constants": {"T": RL_T},
            "parameters": [{"name": "R", "value": R, "lower": 0, "unit": "ohm"},
                           {"name": "L", "value": L, "lower": 0, "unit": "H"}],
            "equations": {"i": "(1 - T*R/L)*i + T/L*u"}, "discrete": {"sample_time": RL_T}}


def rl_experiment(t, u, i) -> dict:
    return {"name": "rl", "time": t.tolist(), "inputs": {"u": u.tolist()}, "outputs": {"i": i.tolist()}}


SEED004_T = 1e-3
FIRST_ORDER = ([200.0], [1.0, 100.0])
SECOND_ORDER = ([20000.0], [1.0, 2.0, 10000.0])


def simulate_seed004(system, duration: float = 10.0, noise_power: float = 1e-5, seed: int = 0):
    """(t, u, y) of seed 004's experiment: exact ZOH response plus white noise of the given power."""
    n = int(round(duration / SEED004_T))
    t = np.arange(n) * SEED004_T
    u = np.sin(2 * np.pi * 2 * t) + 0.1 * np.sin(2 * np.pi * 20 * t)
    num, den, _ = signal.cont2discrete(system, SEED004_T, method="zoh")
    y = signal.lfilter(np.ravel(num), den, u)
    rng = np.random.default_rng(seed)
    return t, u, y + np.sqrt(noise_power) * rng.standard_normal(n)


def first_order_model(guess=(50.0, 100.0)) -> dict:
    """200/(s+100) sampled with a zero-order hold, in its physical parameters ap, bp."""
    return {"name": "first_order", "states": ["y"], "inputs": ["u"], "constants": {"T": SEED004_T},
            "parameters": [{"name": "ap", "value": guess[0]}, {"name": "bp", "value": guess[1]}],
            "equations": {"y": "exp(-ap*T)*y + bp/ap*(1 - exp(-ap*T))*u"},
            "discrete": {"sample_time": SEED004_T}}


def second_order_model(guess=(4.0, 9000.0, 15000.0)) -> dict:
    """bp2/(s^2 + ap1 s + ap2) sampled with a zero-order hold (underdamped), in ap1, ap2, bp2.

    States y, y_1 = y[k-1] and u_1 = u[k-1] (delay states, rebuilt from the data)."""
    return {"name": "second_order", "states": ["y", "y_1", "u_1"], "inputs": ["u"],
            "constants": {"T": SEED004_T},
            "parameters": [{"name": "ap1", "value": guess[0]}, {"name": "ap2", "value": guess[1]},
                           {"name": "bp2", "value": guess[2]}],
            "definitions": {"sig": "ap1/2", "wd": "sqrt(ap2 - sig^2)", "K": "bp2/ap2", "E": "exp(-sig*T)",
                            "c": "cos(wd*T)", "s": "sin(wd*T)",
                            "a1": "-2*E*c", "a2": "E^2",
                            "b1": "K*(1 - E*(c + sig/wd*s))", "b2": "K*(E^2 + E*(sig/wd*s - c))"},
            "equations": {"y": "-a1*y - a2*y_1 + b1*u + b2*u_1", "y_1": "y", "u_1": "u"}, "outputs": {"y": "y"},
            "discrete": {"sample_time": SEED004_T}}


def seed004_experiment(t, u, y) -> dict:
    return {"name": "seed004", "time": t.tolist(), "inputs": {"u": u.tolist()}, "outputs": {"y": y.tolist()}}


def rl_continuous_model(R: float = 1.0, L: float = 1.0) -> dict:
    """Seed 003's RL circuit in continuous time, L di/dt = -R i + u, for MRAS."""
    return {"name": "rl_circuit", "states": ["i"], "inputs": ["u"],
            "parameters": [{"name": "R", "value": R, "lower": 0, "unit": "ohm"},
                           {"name": "L", "value": L, "lower": 0, "unit": "H"}],
            "equations": {"i": "(-R*i + u)/L"}}


RLC_TRUTH = {"R": 2.0, "L": 0.5, "C": 0.02}


def simulate_rlc(u: np.ndarray, noise: float = 1e-4, seed: int = 0, ar: float = 0.0) -> np.ndarray:
    """Series RLC (L di/dt = u − R i − v_C, C dv_C/dt = i), voltage held between samples, exact ZOH
    response sampled every 1 ms, plus measurement noise (AR(1) with pole `ar`: coloured when > 0)."""
    p = RLC_TRUTH
    a = np.array([[-p["R"] / p["L"], -1 / p["L"]], [1 / p["C"], 0.0]])
    b = np.array([[1 / p["L"]], [0.0]])
    ad, bd, *_ = signal.cont2discrete((a, b, np.array([[1.0, 0.0]]), np.zeros((1, 1))), RL_T, "zoh")
    x, out = np.zeros(2), np.empty(u.size)
    for k, uk in enumerate(u):
        out[k] = x[0]
        x = ad @ x + bd[:, 0] * uk
    white = np.random.default_rng(seed).standard_normal(u.size)
    coloured = signal.lfilter([np.sqrt(1 - ar * ar)], [1.0, -ar], white)
    return out + noise * coloured


def rlc_model(guess=(1.0, 1.0, 0.01)) -> dict:
    """The RLC circuit's Euler difference equation in R, L, C (the model reference adaptive systems
    chapter, example 7-6): i[k+1] = (2 − TR/L) i + (TR/L − 1 − T²/(LC)) i[k−1] + T/L (u − u[k−1])."""
    return {"name": "rlc_circuit", "states": ["i", "i_1", "u_1"], "inputs": ["u"], "constants": {"T": RL_T},
            "parameters": [{"name": "R", "value": guess[0], "lower": 0, "unit": "ohm"},
                           {"name": "L", "value": guess[1], "lower": 0, "unit": "H"},
                           {"name": "C", "value": guess[2], "lower": 0, "unit": "F"}],
            "equations": {"i": "(2 - T*R/L)*i + (T*R/L - 1 - T^2/(L*C))*i_1 + T/L*u - T/L*u_1",
                          "i_1": "i", "u_1": "u"},
            "outputs": {"i": "i"}, "discrete": {"sample_time": RL_T}}


MOTOR = {"tau_r": 0.1, "M": 0.5, "I": 10.0, "omega_s": 2 * np.pi * 50}


def induction_motor_model(omega_r_guess: float = 100.0) -> dict:
    """Rotor flux of an induction machine in stator coordinates (the model reference adaptive systems
    chapter, example 7-4): the speed ω_r is estimated from the measured fluxes and stator currents."""
    return {"name": "induction_motor", "states": ["psa", "psb"], "inputs": ["isa", "isb"],
            "constants": {"tau_r": MOTOR["tau_r"], "M": MOTOR["M"]},
            "parameters": [{"name": "wr", "value": omega_r_guess, "lower": 0, "unit": "rad/s"}],
            "equations": {"psa": "-psa/tau_r - wr*psb + M/tau_r*isa",
                          "psb": "wr*psa - psb/tau_r + M/tau_r*isb"}}


def simulate_induction_motor(omega_r: float, duration: float = 1.0, ts: float = 1e-3, noise: float = 0.0,
                             seed: int = 0, ripple: float = 0.0):
    """(t, i_sα, i_sβ, ψ_rα, ψ_rβ): sinusoidal stator currents at 50 Hz (plus a 5th-harmonic `ripple`),
    fluxes from solve_ivp (DOP853, rtol 1e-11) from rest, sampled every `ts`, noise relative to |ψ|."""
    from scipy.integrate import solve_ivp
    m = MOTOR
    w5 = -5 * m["omega_s"]

    def currents(t):
        return (m["I"] * (np.cos(m["omega_s"] * t) + ripple * np.cos(w5 * t)),
                m["I"] * (np.sin(m["omega_s"] * t) + ripple * np.sin(w5 * t)))

    def rhs(t, x):
        ia, ib = currents(t)
        return [-x[0] / m["tau_r"] - omega_r * x[1] + m["M"] / m["tau_r"] * ia,
                omega_r * x[0] - x[1] / m["tau_r"] + m["M"] / m["tau_r"] * ib]

    t = np.arange(int(round(duration / ts)) + 1) * ts
    sol = solve_ivp(rhs, (0, t[-1]), [0.0, 0.0], t_eval=t, method="DOP853", rtol=1e-11, atol=1e-12)
    ia, ib = currents(t)
    rng = np.random.default_rng(seed)
    size = float(np.sqrt(np.mean(sol.y ** 2)))
    psa, psb = (y + noise * size * rng.standard_normal(t.size) for y in sol.y)
    return t, ia, ib, psa, psb


def induction_motor_experiment(t, ia, ib, psa, psb) -> dict:
    return {"name": "motor", "time": t.tolist(), "inputs": {"isa": ia.tolist(), "isb": ib.tolist()},
            "outputs": {"psa": psa.tolist(), "psb": psb.tolist()}}
