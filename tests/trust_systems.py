"""Truth systems for the trust Monte Carlo (tests/solvers/test_trust_verdict.py, bench/bench_trust.py).

Two systems other than the mass-spring-damper, simulated independently of greyfit (numpy RK4 on a
fine grid, or scipy), each in the scenarios the verdict must tell apart:

- a thermal RC node (temperature rise x above ambient, heater power P held between samples, a
  PRBS-like digital output): C dx/dt = P - x/R [- h x^2];
- a pendulum measured by its angle only, driven by a smooth torque (a sum of sines, sampled) or by a
  held one:
  dθ/dt = ω, dω/dt = -a sin θ - b ω + u [- cd ω|ω|].

The missing nonlinear term of the "slightly wrong" scenario is scaled so that its RMS is 5 % of the
RMS of the linear term it corrupts (the node's loss x/R, the pendulum's restoring a·sin θ) along the
record. Noise is white Gaussian, a fixed fraction of the output's standard deviation. Every seed
draws a new input and a new noise.
"""
from __future__ import annotations

import numpy as np
from scipy.integrate import solve_ivp

THERMAL_TRUTH = {"C": 40.0, "R": 0.5}
PENDULUM_TRUTH = {"a": 9.81, "b": 0.3}
MISSING_FRACTION = 0.05
HOLD_SAMPLES = 4   # a held input is recognisable only where it holds for more than one sample


def _prbs(n: int, hold: int, rng: np.random.Generator, low: float, high: float) -> np.ndarray:
    """Random binary levels, each held for a random multiple (1-3) of `hold` samples."""
    out = np.empty(n)
    k, level = 0, rng.integers(2)
    while k < n:
        width = hold * int(rng.integers(1, 4))
        out[k:k + width] = high if level else low
        level = 1 - level
        k += width
    return out


def _held_rk4(rhs, x0: np.ndarray, t: np.ndarray, u: np.ndarray, fine: int = 40) -> np.ndarray:
    """States at the samples, the input held over each interval, RK4 with `fine` steps per interval."""
    x = np.empty((x0.size, t.size))
    x[:, 0] = xk = x0
    for k in range(t.size - 1):
        h = (t[k + 1] - t[k]) / fine
        for _ in range(fine):
            k1 = rhs(xk, u[k])
            k2 = rhs(xk + h / 2 * k1, u[k])
            k3 = rhs(xk + h / 2 * k2, u[k])
            k4 = rhs(xk + h * k3, u[k])
            xk = xk + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        x[:, k + 1] = xk
    return x


# --- thermal RC node -------------------------------------------------------------------------------

def thermal_model(interpolation: str | None = None, substeps: int | None = None) -> dict:
    return {"name": "thermal_node", "states": ["x"], "inputs": ["P"],
            "parameters": [{"name": "C", "value": 25.0, "lower": 0.1, "upper": 1000.0, "unit": "J/K"},
                           {"name": "R", "value": 1.0, "lower": 0.01, "upper": 100.0, "unit": "K/W"}],
            "equations": {"x": "(P - x/R)/C"}, "outputs": {"x": "x"}}


def thermal_record(seed: int, n: int = 300, dt: float = 1.0, quadratic: bool = False,
                   noise: float = 0.01, truth: dict | None = None, hold: int = 5) -> dict:
    """One experiment: P a held PRBS 0/50 W; `quadratic`: a loss h x^2 at 5 % of x/R is added."""
    p = dict(THERMAL_TRUTH if truth is None else truth)
    rng = np.random.default_rng(seed)
    t = np.arange(n) * dt
    u = _prbs(n, hold, rng, 0.0, 50.0)

    def linear(x, uu):
        return (uu - x / p["R"]) / p["C"]
    x = _held_rk4(linear, np.zeros(1), t, u)[0]
    if quadratic:
        # h such that rms(h x^2) = 5 % of rms(x/R) on the linear trajectory (then re-simulated)
        h = MISSING_FRACTION * np.sqrt(np.mean((x / p["R"]) ** 2)) / np.sqrt(np.mean(x ** 4))
        x = _held_rk4(lambda xx, uu: (uu - xx / p["R"] - h * xx ** 2) / p["C"], np.zeros(1), t, u)[0]
    y = x + noise * np.std(x) * rng.standard_normal(n)
    return {"name": "heat", "time": t.tolist(), "inputs": {"P": u.tolist()}, "outputs": {"x": y.tolist()},
            "initial_state": {"x": 0.0}}


# --- pendulum ---------------------------------------------------------------------------------------

def pendulum_model() -> dict:
    return {"name": "pendulum", "states": ["theta", "omega"], "inputs": ["u"],
            "parameters": [{"name": "a", "value": 8.5, "lower": 0.1, "upper": 100.0, "unit": "1/s^2"},
                           {"name": "b", "value": 0.5, "lower": 0.0, "upper": 10.0, "unit": "1/s"}],
            "equations": {"theta": "omega", "omega": "-a*sin(theta) - b*omega + u"},
            "outputs": {"theta": "theta"}}


class _Sines:
    def __init__(self, rng: np.random.Generator, amplitude: float = 1.5, w_max: float = 4.0):
        self.w = rng.uniform(0.3, w_max, 5)
        self.phi = rng.uniform(0, 2 * np.pi, 5)
        self.amp = amplitude / np.sqrt(5)

    def __call__(self, t):
        return self.amp * np.sum(np.sin(np.multiply.outer(t, self.w) + self.phi), axis=-1)


def pendulum_record(seed: int, n: int = 300, dt: float = 0.05, drag: bool = False, held: bool = False,
                    noise: float = 0.01, truth: dict | None = None, w_max: float = 4.0,
                    linear: bool = False) -> dict:
    """Angle only; torque a sum of sines (`held`: sampled and held, a digital controller's output;
    `linear`: interpolated linearly between the samples, so that first-order hold is exact).

    `drag`: quadratic drag cd ω|ω| at 5 % of the RMS of a·sin θ is added."""
    p = dict(PENDULUM_TRUTH if truth is None else truth)
    rng = np.random.default_rng(10_000 + seed)
    t = np.arange(n) * dt
    sines = _Sines(rng, w_max=w_max)
    u = sines(t)
    if held:   # a digital controller updating every HOLD_SAMPLES samples, its output held in between
        u = np.repeat(u[::HOLD_SAMPLES], HOLD_SAMPLES)[:n]
    x0 = np.array([0.2, 0.0])

    def rhs_of(cd):
        return lambda x, uu: np.array([x[1], -p["a"] * np.sin(x[0]) - p["b"] * x[1] - cd * x[1] * abs(x[1]) + uu])

    def simulate(cd):
        if held:
            return _held_rk4(rhs_of(cd), x0, t, u, fine=20)
        f = rhs_of(cd)
        drive = (lambda tt: float(np.interp(tt, t, u))) if linear else (lambda tt: float(sines(tt)))
        sol = solve_ivp(lambda tt, x: f(x, drive(tt)), (0, t[-1]), x0, t_eval=t, method="DOP853",
                        rtol=1e-10, atol=1e-12, max_step=dt / 4 if linear else dt)
        return sol.y
    x = simulate(0.0)
    if drag:
        w = x[1]
        cd = MISSING_FRACTION * np.sqrt(np.mean((p["a"] * np.sin(x[0])) ** 2)) / np.sqrt(np.mean(w ** 4))
        x = simulate(cd)
    y = x[0] + noise * np.std(x[0]) * rng.standard_normal(n)
    return {"name": "swing", "time": t.tolist(), "inputs": {"u": u.tolist()}, "outputs": {"theta": y.tolist()},
            "initial_state": {"theta": 0.2, "omega": 0.0}}


# --- the scenarios of the verdict's Monte Carlo --------------------------------------------------------

ALIASED_THERMAL = {"C": 0.8, "R": 1.0}   # τ = 0.8 s sampled every 0.8 s: |λ|Δt = 1


def _request(model: dict, exp: dict, options: dict) -> dict:
    return {"model": model, "experiments": [exp], "method": "multiple_shooting", "options": options}


def thermal_scenario(name: str, seed: int) -> dict:
    """A fit request; `name`: correct, held_as_linear, wrong_model, aliased (1 substep), aliased_auto."""
    model = thermal_model()
    if name in ("aliased", "aliased_auto"):
        model["parameters"][0]["value"] = 0.5
        exp = thermal_record(seed, n=200, dt=0.8, truth=ALIASED_THERMAL, hold=2)
        return _request(model, exp, {"substeps": 1} if name == "aliased" else {})
    exp = thermal_record(seed, quadratic=name == "wrong_model")
    return _request(model, exp, {"input_interpolation": "foh"} if name == "held_as_linear" else {})


def pendulum_scenario(name: str, seed: int) -> dict:
    """As `thermal_scenario`. The torque is a real input: a sum of sines sampled at ω·Δt ≤ 0.2 (a
    continuous signal, not the ramps between samples that foh assumes); `linear_torque` is the same
    torque made of ramps, for the one scenario where reading it as linear is right."""
    model = pendulum_model()
    if name in ("aliased", "aliased_auto"):
        exp = pendulum_record(seed, n=120, dt=0.25, w_max=1.2)
        return _request(model, exp, {"substeps": 1} if name == "aliased" else {})
    if name == "held_as_linear":
        return _request(model, pendulum_record(seed, held=True), {"input_interpolation": "foh"})
    if name == "linear_torque":
        return _request(model, pendulum_record(seed, linear=True), {"input_interpolation": "foh"})
    return _request(model, pendulum_record(seed, drag=name == "wrong_model"), {})


SCENARIOS = {"thermal": thermal_scenario, "pendulum": pendulum_scenario}
TRUTH = {"thermal": THERMAL_TRUTH, "pendulum": PENDULUM_TRUTH}
