"""Random misspecified systems for the trust benchmark (issue 38; bench/bench_trust.py).

A seed draws a physical block (tests/generators/blocks.py: DC motor, two-compartment
pharmacokinetics, quarter car, two thermal nodes, pendulum, cascaded tanks, a reactor; 2-4 states,
linear and nonlinear, one to two outputs measured), its parameters (±15 % around nominal), the
initial guess (±20 % around the truth), an input (held: random levels re-set every `hold` samples;
smooth: a sum of sines sampled at ωΔt ≤ 0.2), noise (white or AR(1), 1 % of each output's spread)
and a validation record made the same way. A scenario is what the declared model gets wrong:

  right              nothing
  sensor_lag         a first-order lag τ = 1-2 Δt in the first output's sensor (a state the model lacks)
  input_filter       a first-order lag τ = 1-2 Δt between the commanded and the applied input
  missing_state      a deep third compartment (pharmacokinetics)
  quadratic          a small quadratic loss or damping (motor, thermal node, pendulum)
  asymmetric_damper  a damper stiffer one way than the other (quarter car)
  saturable          a Michaelis-Menten elimination or a saturable reaction rate (pharmacokinetics, reactor)
  held_read_smooth   the right model, an input re-set every 1-2 samples read at `auto` (as a smooth curve)

and two that no check was developed on (issue 38: the rates must hold beyond the blocks looked at):

  right_heldout      nothing, on a held-out block (an RC ladder measured at its second node)
  power_loss         a small loss growing as |x|^1.5 (a law no screened effect names: between a linear
                     and a quadratic one) on the motor, the thermal node, the pendulum or the RC ladder

The true structure is the declared model with the misspecification's terms added and free, so the
two are nested and a likelihood-ratio test says whether the data can show the misspecification.
The truth is simulated here (numpy RK4, 20 steps per sample), independently of greyfit.
"""
from __future__ import annotations

import re
from dataclasses import dataclass, replace

import numpy as np

from tests.generators.blocks import ALL_BLOCKS, BLOCKS, Block

SPREAD, GUESS_SPREAD, NOISE = 0.15, 0.2, 0.01
AR_COEFFICIENT = 0.8
FINE = 20
SCENARIOS = ["right", "sensor_lag", "input_filter", "missing_state", "quadratic", "asymmetric_damper",
             "saturable", "held_read_smooth", "right_heldout", "power_loss"]   # new ones last: a
#                                                             scenario's index seeds its draws
# which blocks carry which misspecification, and the extra terms' sizes (drawn per seed)
SUPPORTS = {"quadratic": ["dc_motor", "thermal_two_node", "pendulum"], "asymmetric_damper": ["quarter_car"],
            "saturable": ["pk_two_compartment", "reactor"], "missing_state": ["pk_two_compartment"],
            "right_heldout": ["rc_ladder"], "power_loss": ["dc_motor", "thermal_two_node", "pendulum", "rc_ladder"]}


@dataclass
class Case:
    """One generated fit: the declared request, the true-structure request and the truth."""

    block: str
    scenario: str
    noise: str
    input_kind: str
    declared: dict          # the fit request of the declared model
    true_structure: dict    # the same records, the model with the misspecification's terms free
    truth: dict[str, float]   # the declared model's free parameters' true values
    extra: list[str]        # the true structure's added parameters


def _extras(scenario: str, block: str, rng: np.random.Generator, dt: float) -> dict[str, float]:
    if scenario == "quadratic":
        return {"h": 4e-4 * rng.uniform(1, 2)} if block == "thermal_two_node" else \
            {"d": (2e-4 if block == "dc_motor" else 0.05) * rng.uniform(1, 2)}
    if scenario == "power_loss":   # about the quadratic scenario's loss at a typical level
        size = {"dc_motor": ("d15", 9e-4), "thermal_two_node": ("h15", 2e-3), "pendulum": ("d15", 0.07),
                "rc_ladder": ("g15", 3e-3)}[block]
        return {size[0]: size[1] * rng.uniform(1, 2)}
    if scenario == "asymmetric_damper":
        return {"a": rng.uniform(0.1, 0.2)}
    if scenario == "saturable":
        return {"s": rng.uniform(0.01, 0.02) if block == "pk_two_compartment" else rng.uniform(0.3, 0.6)}
    if scenario == "missing_state":
        return {"k13": 0.05, "k31": 0.02}
    if scenario in ("sensor_lag", "input_filter"):
        return {"tau_s" if scenario == "sensor_lag" else "tau_u": dt * rng.uniform(1, 2)}
    return {}


def _with_sensor_lag(b: Block, tau: float) -> Block:
    """The first output read through a first-order lag: a state `ys` the declared model lacks."""
    name, j = next(iter(b.outputs)), 0
    nx = len(b.states)

    def rhs(x, u, p):
        return np.append(b.rhs(x[:nx], u, p), (b.out(x[:nx], p)[j] - x[nx]) / tau)

    def out(x, p):
        y = b.out(x[:nx], p).copy()
        y[j] = x[nx]
        return y
    return replace(b, states=b.states + ["ys"], equations={**b.equations, "ys": f"({b.outputs[name]} - ys)/tau_s"},
                   outputs={**b.outputs, name: "ys"}, rhs=rhs, out=out, x0=np.append(b.x0, b.out(b.x0, b.truth)[j]))


def _with_input_filter(b: Block, tau: float, u0: float) -> Block:
    """The input applied through a first-order lag: a state `uf` the declared model lacks."""
    nx = len(b.states)
    eqs = {s: re.sub(r"\bu\b", "uf", e) for s, e in b.equations.items()}

    def rhs(x, u, p):
        return np.append(b.rhs(x[:nx], x[nx], p), (u - x[nx]) / tau)
    return replace(b, states=b.states + ["uf"], equations={**eqs, "uf": "(u - uf)/tau_u"}, rhs=rhs,
                   out=lambda x, p: b.out(x[:nx], p), x0=np.append(b.x0, u0))


class Input:
    """Held random levels (re-set every `hold` samples, 1-3 drawn per level) or a sum of sines."""

    def __init__(self, b: Block, kind: str, rng: np.random.Generator, hold: tuple[int, int] = (2, 4)):
        lo, hi = b.u_range
        self.kind, self.dt = kind, b.dt
        if kind == "held":
            levels, k = [], 0
            while k < b.n:
                width = int(rng.integers(hold[0], hold[1] + 1))
                levels += [rng.uniform(lo, hi)] * width
                k += width
            self.levels = np.array(levels[:b.n])
        else:
            self.w = rng.uniform(0.1, 1.0, 5) * min(b.u_omega, 0.2 / b.dt)
            self.phi = rng.uniform(0, 2 * np.pi, 5)
            self.centre, self.amp = (lo + hi) / 2, (hi - lo) / 6   # the peaks stay in the range

    def __call__(self, t: float) -> float:
        if self.kind == "held":
            return float(self.levels[min(int(t / self.dt + 1e-9), self.levels.size - 1)])
        return float(self.centre + self.amp * np.sum(np.sin(self.w * t + self.phi)))


def simulate(b: Block, p: dict, u: Input) -> np.ndarray:
    """Outputs at the samples (n_out, n), RK4 with `FINE` steps per sample, the input read at each stage."""
    h = b.dt / FINE
    x, ys = b.x0.astype(float), [b.out(b.x0, p)]
    for k in range(b.n - 1):
        t = k * b.dt
        for m in range(FINE):
            tm = t + m * h
            if u.kind == "held":   # constant over the sample interval, whatever the stage time says
                uk = u(t)
                k1 = b.rhs(x, uk, p)
                k2 = b.rhs(x + h / 2 * k1, uk, p)
                k3 = b.rhs(x + h / 2 * k2, uk, p)
                k4 = b.rhs(x + h * k3, uk, p)
            else:
                k1 = b.rhs(x, u(tm), p)
                k2 = b.rhs(x + h / 2 * k1, u(tm + h / 2), p)
                k3 = b.rhs(x + h / 2 * k2, u(tm + h / 2), p)
                k4 = b.rhs(x + h * k3, u(tm + h), p)
            x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        ys.append(b.out(x, p))
    return np.array(ys).T


def noise(n: int, kind: str, rng: np.random.Generator) -> np.ndarray:
    """Unit-variance white or stationary AR(1) noise."""
    e = rng.standard_normal(n)
    if kind == "white":
        return e
    v = np.empty(n)
    v[0] = e[0]
    for k in range(1, n):
        v[k] = AR_COEFFICIENT * v[k - 1] + np.sqrt(1 - AR_COEFFICIENT ** 2) * e[k]
    return v


def _record(name: str, b: Block, declared: Block, p: dict, u: Input, kind: str, rng,
            sigma: np.ndarray | None) -> tuple[dict, np.ndarray]:
    """A record and its noise levels (`sigma`, or 1 % of each output's spread here: the validation
    record is measured by the same sensors as the fitted one)."""
    y = simulate(b, p, u)
    t = np.arange(b.n) * b.dt
    sigma = NOISE * np.std(y, axis=1) if sigma is None else sigma
    outputs = {o: (y[c] + sigma[c] * noise(b.n, kind, rng)).tolist() for c, o in enumerate(b.outputs)}
    x0 = dict(zip(declared.states, declared.x0.tolist()))
    return {"name": name, "time": t.tolist(), "inputs": {"u": [u(tk) for tk in t]}, "outputs": outputs,
            "initial_state": x0}, sigma


def _model(b: Block, free: dict[str, float], fixed: dict[str, float]) -> dict:
    params = [{"name": k, "value": v, "lower": v / 100, "upper": v * 100} for k, v in free.items()]
    params += [{"name": k, "value": v, "fixed": True} for k, v in fixed.items()]
    return {"name": b.name, "states": b.states, "inputs": ["u"], "parameters": params,
            "equations": b.equations, "outputs": b.outputs}


def _true_block(name: str, extras: dict, u0: float, samples: int) -> Block:
    base = {k: v for k, v in extras.items() if k not in ("tau_s", "tau_u")}
    b = replace(ALL_BLOCKS[name](base), n=samples)
    if "tau_s" in extras:
        b = _with_sensor_lag(b, extras["tau_s"])
    if "tau_u" in extras:
        b = _with_input_filter(b, extras["tau_u"], u0)
    return b


def make_case(scenario: str, seed: int, noise_kind: str = "white", input_kind: str | None = None,
              samples: int | None = None) -> Case:
    """One random fit of `scenario` (see the module's list); `input_kind` held, smooth or None (drawn);
    `samples` per record (None: the block's own, 240-400)."""
    rng = np.random.default_rng([SCENARIOS.index(scenario), seed, noise_kind == "ar1"])
    names = SUPPORTS.get(scenario, list(BLOCKS))
    block = names[int(rng.integers(len(names)))]
    declared = ALL_BLOCKS[block]({})
    if samples is not None:
        declared = replace(declared, n=samples)
    kind = "held" if scenario == "held_read_smooth" else input_kind or ("held" if rng.random() < 0.5 else "smooth")
    hold = (1, 2) if scenario == "held_read_smooth" else (2, 4)
    p = {k: v * float(np.exp(SPREAD * rng.standard_normal())) if k in declared.free else v
         for k, v in declared.truth.items()}
    extras = _extras(scenario, block, rng, declared.dt)
    records, sigma = [], None
    for name in ("fit", "validation"):
        u = Input(declared, kind, rng, hold)
        truth = _true_block(block, extras, u(0.0), declared.n)
        record, sigma = _record(name, truth, declared, p, u, noise_kind, rng, sigma)
        records.append(record)
    guess = {k: p[k] * float(np.exp(GUESS_SPREAD * rng.standard_normal())) for k in declared.free}
    fixed = {k: v for k, v in p.items() if k not in declared.free}
    request = {"model": _model(declared, guess, fixed), "experiments": [records[0]], "validation": [records[1]]}
    true_extras = {k: v for k, v in extras.items()}
    tb = _true_block(block, true_extras, 0.0, declared.n)
    true_model = _model(tb, {**{k: p[k] for k in declared.free}, **true_extras}, fixed)
    true_records = [_with_extra_initial_states(r, tb, declared, p) for r in records]
    true_request = {"model": true_model, "experiments": [true_records[0]], "validation": [true_records[1]]}
    if scenario == "held_read_smooth":   # the truth is the same model with the input read as held
        true_request["options"] = {"input_interpolation": "zoh"}
    return Case(block, scenario, noise_kind, kind, request, true_request, {k: p[k] for k in declared.free},
                list(true_extras))


def _with_extra_initial_states(record: dict, tb: Block, declared: Block, p: dict) -> dict:
    """The record for the true structure: the initial values of its extra states (a sensor at rest on
    its output's initial value, a filtered input at the first input sample)."""
    x0 = dict(record["initial_state"])
    if "ys" in tb.states:
        x0["ys"] = float(declared.out(declared.x0, p)[0])
    if "uf" in tb.states:
        x0["uf"] = float(record["inputs"]["u"][0])
    if "A3" in tb.states:
        x0["A3"] = 0.0
    return {**record, "initial_state": x0}
