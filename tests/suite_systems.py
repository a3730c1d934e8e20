"""System families of bench/bench_discovery_suite.py (and of the tests that pin its findings): a
pendulum measured by its angle, two cascaded tanks measured at the lower level, a motor whose speed
sensor cannot see the sign, and a mass-spring-damper whose position sensor reads with an offset.
Each comes with the undeclared effect or without it (a complete model), white or AR(1) measurement
noise, the input interpolated linearly or held between samples, and a validation record from another
seed. Truth is simulated with scipy (odeint told where the input has kinks, or interval by interval
for a held input), independently of greyfit.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.integrate import odeint

from tests import coloured_records as cr
from tests import partial_systems as ps
from tests.systems import MSD_TRUTH, msd_input, msd_model

Rhs = Callable[[float, np.ndarray, float], list]


def simulate(rhs: Rhs, t: np.ndarray, x0: list[float], u: np.ndarray, held: bool) -> np.ndarray:
    """States (n_states, N) with the input held over each interval, or linear between the samples."""
    if held:
        return cr._simulate_held(rhs, t, x0, u)
    dt = float(t[1] - t[0])
    t0 = float(t[0])
    return odeint(lambda s, tt: rhs(tt, s, cr._linear(u, dt, tt - t0)), x0, t, tcrit=t, rtol=1e-11,
                  atol=1e-12, hmax=dt / 2).T


def noisy(y: np.ndarray, kind: str, seed: int, level: float = 0.01, rho: float = 0.8) -> list[float]:
    e = cr.coloured_noise(y.size, kind, np.random.default_rng(seed), rho=rho)
    return (y + level * np.std(y) * e).tolist()


@dataclass(frozen=True)
class Case:
    """A generated discovery request and what a right answer is."""
    body: dict
    truth: dict[str, float]          # declared free parameters and their true values ({}: not comparable)
    effect: str | None               # the effect the loop should add (None: nothing)
    equation: str | None             # the equation (or output) it acts on


# --- pendulum measured by its angle; undeclared quadratic drag cd ω|ω| ------------------------------
PENDULUM = {"a": 9.81, "b": 0.3, "cd": 0.4}


def _pendulum_input(t: np.ndarray, seed: int) -> np.ndarray:
    return ps.multisine(t, [0.11, 0.23, 0.41, 0.67], [2.4, 2.0, 1.6, 1.2], seed)


def _pendulum_record(seed: int, effect: bool, kind: str, held: bool, name: str, n: int = 1000,
                     dt: float = 0.05) -> dict:
    t = np.arange(n) * dt
    u = _pendulum_input(t, seed)
    cd = PENDULUM["cd"] if effect else 0.0

    def rhs(tt, s, uu):
        return [s[1], -PENDULUM["a"] * np.sin(s[0]) - PENDULUM["b"] * s[1] - cd * s[1] * abs(s[1]) + uu]
    x = simulate(rhs, t, [0.2, 0.0], u, held)
    return {"name": name, "time": t.tolist(), "inputs": {"u": u.tolist()},
            "outputs": {"theta": noisy(x[0], kind, 3000 + seed)}}


def pendulum_case(effect: bool, kind: str, held: bool, seed: int) -> Case:
    model = {"name": "pendulum", "states": ["theta", "omega"], "inputs": ["u"],
             "parameters": [{"name": "a", "value": 8.0, "lower": 0.1, "upper": 100.0},
                            {"name": "b", "value": 0.6, "lower": 0.0, "upper": 10.0}],
             "equations": {"theta": "omega", "omega": "-a*sin(theta) - b*omega + u"},
             "outputs": {"theta": "theta"}}
    body = {"model": model, "experiments": [_pendulum_record(seed, effect, kind, held, "est")],
            "validation": [_pendulum_record(seed + 500, effect, kind, held, "val")]}
    return Case(body, {"a": PENDULUM["a"], "b": PENDULUM["b"]}, "quadratic_drag" if effect else None, "omega")


# --- two cascaded tanks, lower level measured; outflows declared linear (or, complete, as sqrt) -------
def _tanks_record(seed: int, kind: str, held: bool, name: str, n: int = 1001, dt: float = 0.5) -> dict:
    t = np.arange(n) * dt
    u = ps.tanks_input(t, seed)
    a1, a2 = ps.TANKS_TRUTH["a1"], ps.TANKS_TRUTH["a2"]

    def rhs(tt, h, uu):
        q1 = a1 * np.sqrt(max(h[0], 0.0))
        return [uu - q1, q1 - a2 * np.sqrt(max(h[1], 0.0))]
    x = simulate(rhs, t, [0.36, 0.56], u, held)
    return {"name": name, "time": t.tolist(), "inputs": {"u": u.tolist()},
            "outputs": {"h2m": noisy(x[1], kind, 4000 + seed)}}


def tanks_case(effect: bool, kind: str, held: bool, seed: int) -> Case:
    model = ps.tanks_model()
    truth: dict[str, float] = {}
    if not effect:   # the complete model: both outflows through an orifice
        model["equations"] = {"h1": "u - k1*sqrt(max(h1, 0))", "h2": "k1*sqrt(max(h1, 0)) - k2*sqrt(max(h2, 0))"}
        truth = {"k1": ps.TANKS_TRUTH["a1"], "k2": ps.TANKS_TRUTH["a2"]}
    body = {"model": model, "experiments": [_tanks_record(seed, kind, held, "est")],
            "validation": [_tanks_record(seed + 500, kind, held, "val")], "method": "single_shooting"}
    return Case(body, truth, "sqrt_flow" if effect else None, "h2")


# --- a motor whose speed sensor reads |w| -----------------------------------------------------------
def _speed_record(seed: int, effect: bool, kind: str, held: bool, name: str, n: int = 1001,
                  dt: float = 0.02) -> dict:
    t = np.arange(n) * dt
    u = ps.multisine(t, [0.1, 0.27, 0.55], [1.0, 0.7, 0.5], seed)
    x = simulate(lambda tt, w, uu: [-ps.SPEED_TRUTH["b"] * w[0] + ps.SPEED_TRUTH["K"] * uu], t, [0.0], u, held)
    y = np.abs(x[0]) if effect else x[0]
    return {"name": name, "time": t.tolist(), "inputs": {"u": u.tolist()},
            "outputs": {"y": noisy(y, kind, 5000 + seed)}}


def speed_case(effect: bool, kind: str, held: bool, seed: int) -> Case:
    body = {"model": ps.speed_model(), "experiments": [_speed_record(seed, effect, kind, held, "est")],
            "validation": [_speed_record(seed + 500, effect, kind, held, "val")]}
    return Case(body, dict(ps.SPEED_TRUTH), "output_abs" if effect else None, "y")


# --- mass-spring-damper whose position sensor reads 0.02 m high ----------------------------------------
SENSOR_OFFSET = 0.02


def _offset_record(seed: int, kind: str, held: bool, name: str, x0, t0: float, n: int = 1001,
                   dt: float = 0.02) -> dict:
    t = t0 + np.arange(n) * dt
    u = msd_input(t)
    p = MSD_TRUTH

    def rhs(tt, s, uu):
        return [s[1], (uu - p["c"] * s[1] - p["k"] * s[0]) / p["m"]]
    x = simulate(rhs, t, list(x0), u, held)
    return {"name": name, "time": t.tolist(), "inputs": {"u": u.tolist()},
            "outputs": {"x": noisy(x[0] + SENSOR_OFFSET, kind, 6000 + seed)}}


def sensor_offset_case(kind: str, held: bool, seed: int) -> Case:
    model = msd_model()
    model["outputs"] = {"x": "x"}
    body = {"model": model, "experiments": [_offset_record(seed, kind, held, "est", (0.1, 0.0), 0.0)],
            "validation": [_offset_record(seed + 500, kind, held, "val", (-0.2, 0.1), 20.0)]}
    return Case(body, {"c": MSD_TRUTH["c"], "k": MSD_TRUTH["k"]}, "output_offset", "x")


# --- mass-spring-damper with an undeclared force, position or both states measured ----------------------
N_MSD = 1001
MSD_EFFECTS = {   # name -> (force added to m x'', the loop's effect name, its equation, SINDy's term)
    "none": (None, None, None, None),
    "coulomb": (lambda x, v: 0.5 * np.tanh(v / 1e-3), "coulomb", "v", None),
    "cubic": (lambda x, v: 3.0 * x ** 3, "cubic_stiffness", "v", "x0^3"),
    "drag": (lambda x, v: 0.6 * v * np.abs(v), "quadratic_drag", "v", None),
}


def _msd_states_record(seed: int, kind: str, held: bool, both: bool, force, name: str, x0, t0: float) -> dict:
    """Like tests/coloured_records.msd_record, with the speed measured too when `both`."""
    base = cr.msd_record(N_MSD, seed, kind=kind, level=0.01, extra_force=force, held=held, name=name, x0=x0, t0=t0)
    if both:
        t = np.array(base["time"])
        clean = cr.msd_record(N_MSD, seed, kind="white", level=0.0, extra_force=force, held=held, x0=x0, t0=t0)
        speed = np.gradient(np.array(clean["outputs"]["x"]), t)
        noise = cr.coloured_noise(N_MSD, kind, np.random.default_rng(7000 + seed), rho=0.8)
        base["outputs"]["v"] = (speed + 0.01 * np.std(speed) * noise).tolist()
    return base


def msd_case(effect: str, outputs: str, kind: str, held: bool, seed: int) -> Case:
    """`effect` a key of MSD_EFFECTS; `outputs` "x" (position) or "xv" (both states)."""
    force, name, equation, _ = MSD_EFFECTS[effect]
    recs = [_msd_states_record(s, kind, held, outputs == "xv", force, n, x0, t0)
            for n, s, x0, t0 in (("est", seed, (0.1, 0.0), 0.0), ("val", seed + 500, (-0.2, 0.1), 20.0))]
    model = msd_model()
    model["outputs"] = {o: o for o in ("x", "v")} if outputs == "xv" else {"x": "x"}
    return Case({"model": model, "experiments": [recs[0]], "validation": [recs[1]]},
                {"c": MSD_TRUTH["c"], "k": MSD_TRUTH["k"]}, name, equation)


FAMILIES: dict[str, Callable[..., Case]] = {
    "pendulum": pendulum_case, "tanks": tanks_case, "speed": speed_case,
}
