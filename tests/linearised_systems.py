"""ODE models for linearised frequency fits, with their frequency responses worked out by hand.

* Seed 001's plant P(s) = (b1 s² + b2)/(s (s³ + a1 s² + a2 s + a3)) in controllable canonical form
  (z1' = z2, z2' = z3, z3' = z4, z4' = u − a3 z2 − a2 z3 − a1 z4, y = b2 z1 + b1 z3): linear, so the
  linearisation at the origin is the plant itself (the truth is `tests/frequency_systems.response`).
* A damped pendulum driven by a torque, m l² θ'' = τ − m g l sin θ − c θ', at the equilibrium of a
  constant torque τ0: sin θ* = τ0/(m g l), so G(s) = 1/(m l² s² + c s + m g l cos θ*). Because
  cos θ* depends on m l, the operating point makes m and l separately identifiable.
* A tank with a square-root outflow, A dh/dt = u − k √h: at the level h0 of an inflow u0 (so
  k = u0/√h0), G(s) = (1/A)/(s + k/(2 A √h0)).
"""
from __future__ import annotations

import numpy as np

from tests.frequency_systems import NAMES, noisy

G_ACC = 9.81

PENDULUM_TRUTH = {"m": 0.5, "l": 0.4, "c": 0.05}
PENDULUM_TORQUE = 1.0       # N m, τ0/(m g l) = 0.51: θ* = 0.535 rad
TANK_TRUTH = {"A": 2.0, "k": 0.5}
TANK_INFLOW = 0.2           # h0 = (u0/k)² = 0.16


def seed001_ode_model(guess: dict, margin: float = 0.01) -> dict:
    params = [{"name": n, "value": guess[n], "lower": 0.0, "upper": 20 * guess[n]} for n in NAMES]
    return {"kind": "linearised_ode", "name": "seed001_ode", "states": ["z1", "z2", "z3", "z4"],
            "inputs": ["u"], "parameters": params, "constants": {"Kp": 1.0, "Ki": 1.0},
            "equations": {"z1": "z2", "z2": "z3", "z3": "z4", "z4": "u - a3*z2 - a2*z3 - a1*z4"},
            "outputs": {"y": "b2*z1 + b1*z3"},
            "constraints": [f"a1*a2 - a3 >= {margin}"],
            "operating_point": {"states": {"z1": 0, "z2": 0, "z3": 0, "z4": 0}, "inputs": {"u": 0},
                                "equilibrium": "given"},
            "feedback": {"controller": {"num": ["Kp", "Ki"], "den": ["1", "0"]}}}


def pendulum_equilibrium(p: dict, torque: float = PENDULUM_TORQUE) -> float:
    return float(np.arcsin(torque / (p["m"] * G_ACC * p["l"])))


def pendulum_response(p: dict, omega: np.ndarray, torque: float = PENDULUM_TORQUE) -> np.ndarray:
    s = 1j * omega
    stiffness = p["m"] * G_ACC * p["l"] * np.cos(pendulum_equilibrium(p, torque))
    return 1.0 / (p["m"] * p["l"] ** 2 * s ** 2 + p["c"] * s + stiffness)


def pendulum_model(guess: dict, torque: float = PENDULUM_TORQUE, start: float = 0.3) -> dict:
    return {"kind": "linearised_ode", "name": "pendulum", "states": ["th", "om"], "inputs": ["tau"],
            "constants": {"g": G_ACC},
            "parameters": [{"name": n, "value": v, "lower": 1e-3, "upper": 10.0} for n, v in guess.items()],
            "equations": {"th": "om", "om": "(tau - m*g*l*sin(th) - c*om)/(m*l^2)"},
            "outputs": {"angle": "th"},
            "operating_point": {"inputs": {"tau": torque}, "states": {"th": start, "om": 0.0},
                                "equilibrium": "solve"}}


def tank_response(p: dict, omega: np.ndarray, inflow: float = TANK_INFLOW) -> np.ndarray:
    h0 = (inflow / p["k"]) ** 2
    return (1.0 / p["A"]) / (1j * omega + p["k"] / (2 * p["A"] * np.sqrt(h0)))


def tank_model(guess: dict, level: float, inflow: float = TANK_INFLOW, equilibrium: str = "given") -> dict:
    return {"kind": "linearised_ode", "name": "tank", "states": ["h"], "inputs": ["q_in"],
            "parameters": [{"name": n, "value": v, "lower": 1e-3, "upper": 100.0} for n, v in guess.items()],
            "equations": {"h": "(q_in - k*sqrt(h))/A"}, "outputs": {"h": "h"},
            "operating_point": {"inputs": {"q_in": inflow}, "states": {"h": level},
                                "equilibrium": equilibrium}}


def response_data(g: np.ndarray, omega: np.ndarray, level: float, seed: int, name: str = "data") -> dict:
    g = noisy(g, level, seed)
    return {"name": name, "omega": list(map(float, omega)), "real": g.real.tolist(), "imag": g.imag.tolist()}
