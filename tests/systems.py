"""Truth systems for tests and benchmarks: exact simulations independent of greyfit (scipy).

Seat model: seed 000 (Ohashi & Hiramoto 2007, Table 1) — 4-DOF seated-driver model under base
excitation w(t), band-limited white noise (variance 0.01, cut-off 100 rad/s), 1 ms sampling.
Motor: seed 002 (Sakaguchi et al. 1982) — linearised shunt DC motor, 3 states and 3 inputs.
"""
from __future__ import annotations

import numpy as np
from scipy.integrate import solve_ivp

SEAT_MASSES = (6.0, 28.0, 10.0, 15.0)
SEAT_TRUTH = {"d1": 400.0, "d2": 4750.0, "d3": 4585.0, "d4": 2064.0,
              "k1": 3.1e5, "k2": 1.83e5, "k3": 1.628e5, "k4": 0.9e5}


class BandLimitedNoise:
    """Sum of equal-amplitude sinusoids up to `cutoff` rad/s with random phases: a flat spectrum
    (band-limited white noise) whose derivative is known exactly."""

    def __init__(self, variance: float, cutoff: float, seed: int, n: int = 200):
        rng = np.random.default_rng(seed)
        self.omega = np.linspace(cutoff / n, cutoff, n)
        self.phase = rng.uniform(0, 2 * np.pi, n)
        self.amp = np.sqrt(2 * variance / n)

    def __call__(self, t):
        return np.sum(self.amp * np.cos(np.multiply.outer(t, self.omega) + self.phase), axis=-1)

    def derivative(self, t):
        return np.sum(-self.amp * self.omega * np.sin(np.multiply.outer(t, self.omega) + self.phase), axis=-1)


def seat_k4_step(t, low=0.9e5, high=1.8e5, switches=(0.25, 0.5, 0.75)):
    """Seed 000 Case 1: k4 alternates low/high at the switch times."""
    n = np.sum(np.greater_equal.outer(np.atleast_1d(t), np.array(switches)), axis=-1)
    out = np.where(n % 2 == 0, low, high)
    return out if np.ndim(t) else float(out[0])


def seat_rhs(t, x, p, w, wd, k4_of_t=None):
    m1, m2, m3, m4 = SEAT_MASSES
    q1, q2, q3, q4, v1, v2, v3, v4 = x
    k4 = p["k4"] if k4_of_t is None else k4_of_t(t)
    a1 = -(p["d1"] * (v1 - v2) + p["k1"] * (q1 - q2)) / m1
    a2 = -(p["d1"] * (v2 - v1) + p["d2"] * (v2 - v3) + p["k1"] * (q2 - q1) + p["k2"] * (q2 - q3)) / m2
    a3 = -(p["d2"] * (v3 - v2) + p["d3"] * (v3 - v4) + p["k2"] * (q3 - q2) + p["k3"] * (q3 - q4)) / m3
    a4 = -(p["d3"] * (v4 - v3) + p["d4"] * (v4 - wd(t)) + p["k3"] * (q4 - q3) + k4 * (q4 - w(t))) / m4
    return np.array([v1, v2, v3, v4, a1, a2, a3, a4])


def simulate_seat(seed: int = 0, n: int = 1000, dt: float = 1e-3, k4_of_t=None, params=None):
    """(t, states (8, n), derivatives (8, n), w, wd) of the seat model from rest."""
    p = dict(SEAT_TRUTH if params is None else params)
    w = BandLimitedNoise(0.01, 100.0, seed)
    t = np.arange(n) * dt
    sol = solve_ivp(lambda tt, x: seat_rhs(tt, x, p, w, w.derivative, k4_of_t), (0, t[-1]), np.zeros(8),
                    t_eval=t, method="DOP853", rtol=1e-11, atol=1e-13, max_step=dt / 2)
    x = sol.y
    dx = np.column_stack([seat_rhs(tt, x[:, i], p, w, w.derivative, k4_of_t) for i, tt in enumerate(t)])
    return t, x, dx, w(t), w.derivative(t)


def seat_model(guess: dict | None = None) -> dict:
    """The seat model in greyfit's JSON contract; masses are known constants (as in seed 000)."""
    g = dict(SEAT_TRUTH if guess is None else guess)
    m1, m2, m3, m4 = SEAT_MASSES
    return {
        "name": "seat_4dof",
        "states": ["q1", "q2", "q3", "q4", "v1", "v2", "v3", "v4"],
        "inputs": ["w", "wd"],
        "constants": {"m1": m1, "m2": m2, "m3": m3, "m4": m4},
        "parameters": [{"name": k, "value": g[k], "lower": 0.0,
                        "unit": "Ns/m" if k.startswith("d") else "N/m"} for k in SEAT_TRUTH],
        "equations": {
            "q1": "v1", "q2": "v2", "q3": "v3", "q4": "v4",
            "v1": "-(d1*(v1 - v2) + k1*(q1 - q2))/m1",
            "v2": "-(d1*(v2 - v1) + d2*(v2 - v3) + k1*(q2 - q1) + k2*(q2 - q3))/m2",
            "v3": "-(d2*(v3 - v2) + d3*(v3 - v4) + k2*(q3 - q2) + k3*(q3 - q4))/m3",
            "v4": "-(d3*(v4 - v3) + d4*(v4 - wd) + k3*(q4 - q3) + k4*(q4 - w))/m4",
        },
    }


def seat_experiment(t, x, w, wd, dx=None, noise: float = 0.0, seed: int = 1) -> dict:
    """Experiment JSON; `noise` is the standard deviation relative to each state's RMS."""
    rng = np.random.default_rng(seed)
    names = ["q1", "q2", "q3", "q4", "v1", "v2", "v3", "v4"]
    outputs = {}
    for i, s in enumerate(names):
        rms = np.sqrt(np.mean(x[i] ** 2))
        outputs[s] = (x[i] + noise * rms * rng.standard_normal(t.size)).tolist()
    exp = {"name": "seat", "time": t.tolist(), "inputs": {"w": w.tolist(), "wd": wd.tolist()},
           "outputs": outputs}
    if dx is not None:
        exp["derivatives"] = {s: dx[i].tolist() for i, s in enumerate(names)}
    return exp


# --- mass-spring-damper: m x'' + c x' + k x = u ------------------------------------------------
MSD_TRUTH = {"m": 2.0, "c": 0.8, "k": 5.0}


def msd_input(t):
    return np.sin(t) + 0.5 * np.sin(3.3 * t) + 0.3 * np.sin(0.7 * t) ** 3


def simulate_msd(t, truth=MSD_TRUTH, x0=(0.1, 0.0), extra_force=None):
    """States (2, N) of the mass-spring-damper; `extra_force(x, v)` adds an undeclared effect."""
    def rhs(tt, s):
        x, v = s
        f = msd_input(tt) - truth["c"] * v - truth["k"] * x
        if extra_force is not None:
            f -= extra_force(x, v)
        return [v, f / truth["m"]]
    sol = solve_ivp(rhs, (t[0], t[-1]), list(x0), t_eval=t, method="DOP853", rtol=1e-11, atol=1e-13,
                    max_step=(t[1] - t[0]) / 2)
    return sol.y


def msd_model(c=0.4, k=3.0, m=2.0, fixed_mass=True) -> dict:
    return {"name": "msd", "states": ["x", "v"], "inputs": ["u"],
            "parameters": [{"name": "m", "value": m, "lower": 0.01, "fixed": fixed_mass},
                           {"name": "c", "value": c, "lower": 0.0},
                           {"name": "k", "value": k, "lower": 0.0}],
            "equations": {"x": "v", "v": "(u - c*v - k*x)/m"}}


def msd_experiment(t, states, noise=0.0, seed=0, name="e1", outputs=("x", "v")) -> dict:
    rng = np.random.default_rng(seed)
    data = {"x": states[0], "v": states[1]}
    return {"name": name, "time": t.tolist(), "inputs": {"u": msd_input(t).tolist()},
            "outputs": {o: (data[o] + noise * rng.standard_normal(t.size)).tolist() for o in outputs}}


# --- seed 002: linearised shunt DC motor, x' = A x + B u (3 states, 3 inputs) ------------------
MOTOR_A = np.array([[-2.0, -0.5, 0.0], [-3.0, -10.0, -1.5], [4.0, 2.0, -0.8]])
MOTOR_B = np.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, -0.5]])
MOTOR_FREE = {"a11": (0, 0), "a12": (0, 1), "a21": (1, 0), "a22": (1, 1), "a23": (1, 2),
              "a31": (2, 0), "a32": (2, 1), "a33": (2, 2)}
MOTOR_B_FREE = {"b11": (0, 0), "b22": (1, 1), "b33": (2, 2)}


def motor_inputs(t, length=5.0):
    """Seed 002's recommendation: one step and two sinusoids of about the record length.

    The step rises over one 5 ms sample, so that first-order-hold interpolation represents it exactly."""
    return np.vstack([np.clip((t - 0.1 * length) / 0.005, 0.0, 1.0),
                      np.sin(2 * np.pi * t / length),
                      np.sin(2 * np.pi * 1.7 * t / length + 0.5)])


def simulate_motor(t):
    def u_of(tt):
        return motor_inputs(np.array([tt]))[:, 0]
    sol = solve_ivp(lambda tt, x: MOTOR_A @ x + MOTOR_B @ u_of(tt), (t[0], t[-1]), np.zeros(3),
                    t_eval=t, method="DOP853", rtol=1e-11, atol=1e-13, max_step=(t[1] - t[0]) / 2)
    return sol.y


def motor_model(factor=1.3) -> dict:
    """Structure of seed 002's eq. (22): zeros known, the 11 nonzero entries unknown."""
    params = []
    for name, (i, j) in {**MOTOR_FREE}.items():
        params.append({"name": name, "value": factor * MOTOR_A[i, j]})
    for name, (i, j) in MOTOR_B_FREE.items():
        params.append({"name": name, "value": factor * MOTOR_B[i, j]})
    return {"name": "shunt_motor", "states": ["x1", "x2", "x3"], "inputs": ["u1", "u2", "u3"],
            "parameters": params,
            "equations": {"x1": "a11*x1 + a12*x2 + b11*u1",
                          "x2": "a21*x1 + a22*x2 + a23*x3 + b22*u2",
                          "x3": "a31*x1 + a32*x2 + a33*x3 + b33*u3"}}


def motor_truth() -> dict:
    out = {n: MOTOR_A[i, j] for n, (i, j) in MOTOR_FREE.items()}
    out.update({n: MOTOR_B[i, j] for n, (i, j) in MOTOR_B_FREE.items()})
    return out
