"""Records shaped like users' data: coloured measurement noise (a sensor's low-pass, AR(1) drift) and
inputs held between samples (a digital controller's zero-order hold). Truth simulated with scipy,
independently of greyfit; position measured only, as in tests/partial_systems.py."""
from __future__ import annotations

import numpy as np
from scipy.integrate import odeint, solve_ivp
from scipy.signal import lfilter

from tests import partial_systems as ps
from tests.systems import MSD_TRUTH, msd_input

NOISE_KINDS = ("white", "lowpass", "ar1")


def coloured_noise(n: int, kind: str, rng: np.random.Generator, pole: float = 0.15, rho: float = 0.9) -> np.ndarray:
    """Unit-variance noise: white; first-order low-pass with its cut-off at `pole` × Nyquist; AR(1) with
    coefficient `rho`. A burn-in keeps the start stationary."""
    burn = 200
    e = rng.standard_normal(n + burn)
    if kind == "white":
        out = e
    elif kind == "lowpass":
        a = float(np.exp(-np.pi * pole))   # the discrete pole of a first-order filter cutting at pole·π rad/sample
        out = lfilter([1 - a], [1, -a], e)
    elif kind == "ar1":
        out = lfilter([1.0], [1, -rho], e)
    else:
        raise ValueError(kind)
    out = out[burn:]
    return out / np.std(out)


def lag1(kind: str, pole: float = 0.15, rho: float = 0.9) -> float:
    """Lag-1 autocorrelation of the noise kind (for the reports)."""
    return {"white": 0.0, "lowpass": float(np.exp(-np.pi * pole)), "ar1": rho}[kind]


def _simulate(rhs, t: np.ndarray, x0) -> np.ndarray:
    """First state at the samples. LSODA (odeint) told where the input has kinks (every sample, for a
    linearly interpolated input): as accurate as DOP853 at rtol 1e-10 (2e-8 apart on the Duffing
    record) at a tenth of the time, which keeps tests over many seeds quick."""
    dt = float(t[1] - t[0])
    return odeint(lambda s, tt: rhs(tt, s), x0, t, tcrit=t, rtol=1e-11, atol=1e-12, hmax=dt / 2)[:, 0]


def _linear(u: np.ndarray, dt: float, tt: float) -> float:
    """The input between samples as greyfit's first-order hold sees it (np.interp, without its
    per-call cost: the truth simulation evaluates it tens of thousands of times)."""
    k = min(max(int(tt / dt), 0), u.size - 2)
    a = tt / dt - k
    return float(u[k] + a * (u[k + 1] - u[k]))


def _simulate_held(rhs, t: np.ndarray, x0, u_samples: np.ndarray) -> np.ndarray:
    """States with the input held constant over each sample interval (integrated interval by interval:
    no step of the integrator straddles a jump of the input)."""
    x = np.empty((len(x0), t.size))
    x[:, 0] = x0
    for k in range(t.size - 1):
        sol = solve_ivp(lambda tt, s, uk=u_samples[k]: rhs(tt, s, uk), (t[k], t[k + 1]), x[:, k], method="DOP853",
                        rtol=1e-10, atol=1e-12)
        x[:, k + 1] = sol.y[:, -1]
    return x


def _msd_rhs(extra_force):
    p = MSD_TRUTH

    def rhs(tt, s, u):
        f = u - p["c"] * s[1] - p["k"] * s[0]
        if extra_force is not None:
            f -= extra_force(s[0], s[1])
        return [s[1], f / p["m"]]
    return rhs


def msd_record(n: int, seed: int, kind: str = "white", level: float = 0.01, extra_force=None, dt: float = 0.02,
               held: bool = False, name: str = "est", x0=(0.1, 0.0), t0: float = 0.0) -> dict:
    """Mass-spring-damper measured in position only; noise `level` × std of the position."""
    t = t0 + np.arange(n) * dt
    u = msd_input(t)
    rhs = _msd_rhs(extra_force)
    if held:
        x = _simulate_held(rhs, t, list(x0), u)[0]
    else:
        x = _simulate(lambda tt, s: rhs(tt, s, float(msd_input(tt))), t, list(x0))
    noise = coloured_noise(n, kind, np.random.default_rng(1000 + seed))
    return {"name": name, "time": t.tolist(), "inputs": {"u": u.tolist()},
            "outputs": {"x": (x + level * np.std(x) * noise).tolist()}}


def duffing_record(n: int, seed: int, kind: str = "white", level: float = 0.01, cubic: bool = True,
                   dt: float = 0.05, held: bool = False, name: str = "est") -> dict:
    """Duffing oscillator (tests/partial_systems.py truth) measured in position; `cubic` False: linear spring."""
    t = np.arange(n) * dt
    p = dict(ps.DUFFING_TRUTH, k3=ps.DUFFING_TRUTH["k3"] if cubic else 0.0)
    u = ps.duffing_input(t, seed)

    def rhs(tt, s, uu):
        return [s[1], (uu - p["d"] * s[1] - p["k"] * s[0] - p["k3"] * s[0] ** 3) / p["m"]]
    if held:
        x = _simulate_held(rhs, t, [0.0, 0.0], u)[0]
    else:
        x = _simulate(lambda tt, s: rhs(tt, s, _linear(u, dt, tt)), t, [0.0, 0.0])
    noise = coloured_noise(n, kind, np.random.default_rng(2000 + seed))
    return {"name": name, "time": t.tolist(), "inputs": {"u": u.tolist()},
            "outputs": {"y": (x + level * np.std(x) * noise).tolist()}}


def duffing_complete_model() -> dict:
    """The Duffing model with its cubic spring declared: nothing is missing."""
    model = ps.duffing_model()
    model["parameters"].append({"name": "k3", "value": 1.0})
    model["equations"]["yd"] = "(u - d*yd - k*y - k3*y^3)/m"
    return model


def msd_position_model() -> dict:
    from tests.systems import msd_model
    model = msd_model()
    model["outputs"] = {"x": "x"}
    return model
