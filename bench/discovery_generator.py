"""A procedural generator of discovery problems: random chains of physical blocks with a random
missing effect, in the library or outside it, or none (a complete model).

A system is a chain of 2-3 blocks (2-5 states), each driven by the one before (the first by the
input u, held between samples at random levels): a mechanical oscillator (position and velocity), a
thermal capacity (a temperature over the ambient 20 °C), an RC circuit (a charge), a tank (a level),
a chemical reactor (a concentration) or a biological population. Every block's principal state is
measured (never the oscillator's velocity: outputs only), with white or AR(1) (ρ 0.8) noise of 1 % of
its spread. The declared model is linear in every block; its parameters are drawn around nominal
values, the declared start 30 % off. The truth adds, by the configuration's group:

- `in`: one effect of the library on a block that can have it (Coulomb friction, quadratic drag or a
  cubic spring on an oscillator; a constant heat source on a thermal block; an orifice outflow on a
  tank; a sensor offset on a measured output; a parameter drifting in time);
- `out`: one effect the library has no family for (Monod kinetics in a reactor or a population, a
  dead zone on the input, a thrust ∝ u·|u| on an oscillator);
- `beyond`: one effect no family is (a Hill consumption of order 2, an input gain that drops above a
  knee): what the generic families add must be flagged;
- `none`: nothing (a complete model).

Truth is simulated with scipy interval by interval (the input is held), independently of greyfit;
a validation record from another input seed continues the estimation record in time.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from tests.suite_systems import Case, noisy, simulate

BLOCKS = ("mech", "thermal", "rc", "tank", "reactor", "population")
PREFIX = {"thermal": "T", "rc": "q", "tank": "h", "reactor": "c", "population": "n"}   # the block's state
IN_LIBRARY = {"mech": ("coulomb", "quadratic_drag", "cubic_stiffness"), "thermal": ("offset",),
              "tank": ("sqrt_flow",), "any": ("output_offset", "parameter_drift")}
# a sensor gain on a chain of linear blocks is the last block's input gain: not identifiable, not drawn
OUT_OF_LIBRARY = {"mech": ("thrust", "dead_zone"), "reactor": ("monod",), "population": ("monod",),
                  "any": ("dead_zone",)}
# beyond the library even with its generic families (which only approximate them): a Hill law of
# order 2 (a sigmoidal consumption), an input whose gain drops by 60 % above a knee
BEYOND = {"reactor": ("hill",), "population": ("hill",), "any": ("knee",)}


@dataclass
class Block:
    kind: str
    states: list[str]
    params: dict[str, float]           # declared free parameters: true values
    equations: dict[str, str]          # declared (the drive is `{d}`)
    measured: str
    extra: Callable | None = None      # the truth's missing term: (x_block, drive, t) -> added to the derivative
    extra_state: str = ""


@dataclass
class System:
    blocks: list[Block] = field(default_factory=list)
    effect: str | None = None
    equation: str | None = None
    sensor: tuple[str, str, float] | None = None     # (output, "offset"/"gain", size)
    dead_zone: float = 0.0
    knee: float = 0.0                                # the input's gain drops to 0.4 above it
    drift: tuple[str, float] | None = None           # (parameter, relative change per unit time)
    # a sensor offset in the output's units, set by the first record: the sensor's, so the same on the
    # validation record (sized on each record's own spread, it differed between them)
    offset: float | None = None


def _block(kind: str, i: int, rng: np.random.Generator) -> Block:
    s = f"{PREFIX.get(kind, 'x')}{i}"
    if kind == "mech":
        x, v = f"x{i}", f"v{i}"
        k, c = float(rng.uniform(2, 6)), float(rng.uniform(0.4, 1.0))
        return Block(kind, [x, v], {f"k{i}": k, f"c{i}": c},
                     {x: v, v: f"-k{i}*{x} - c{i}*{v} + {{d}}"}, x)
    a, b = float(rng.uniform(0.5, 2.0)), float(rng.uniform(0.3, 1.0))
    return Block(kind, [s], {f"a{i}": a, f"b{i}": b}, {s: f"a{i}*{{d}} - b{i}*{s}"}, s)


def _rhs_block(blk: Block, x: np.ndarray, drive: float, t: float, sysm: System) -> list[float]:
    p = dict(blk.params)
    if sysm.drift is not None and sysm.drift[0] in p:
        p[sysm.drift[0]] *= 1 + sysm.drift[1] * t
    if blk.kind == "mech":
        i = blk.states[0][1:]
        dv = -p[f"k{i}"] * x[0] - p[f"c{i}"] * x[1] + drive
        out = [x[1], dv]
    else:
        i = blk.states[0][1:]
        out = [p[f"a{i}"] * drive - p[f"b{i}"] * x[0]]
    if blk.extra is not None:
        j = blk.states.index(blk.extra_state)
        out[j] += blk.extra(x, drive, t)
    return out


def _dead(u: float, width: float) -> float:
    return float(np.sign(u) * max(abs(u) - width, 0.0)) if width > 0 else u


def _knee(u: float, knee: float) -> float:
    return u if knee <= 0 or abs(u) <= knee else float(np.sign(u) * (knee + 0.4 * (abs(u) - knee)))


def generate(group: str, seed: int, n: int = 1000, dt: float = 0.05, noise: str = "ar1") -> Case:
    """One generated problem of a group ("in", "out", "none") and seed: its request and its truth.

    Parameters
    ----------
    group : str
        "in" (a library effect missing), "out" (an effect outside the library missing), "beyond" (one
        that no family is), "none".
    seed : int
        The seed: the system, the effect, the inputs and the noise.
    n, dt : int, float
        Samples and sample time of each record.
    noise : str
        "white" or "ar1".

    Returns
    -------
    Case
        The discovery request's body, the declared parameters' true values, the effect and equation.
    """
    rng = np.random.default_rng(seed)
    kinds = list(rng.choice(BLOCKS, size=int(rng.integers(2, 4)), replace=True))
    blocks = [_block(k, i + 1, rng) for i, k in enumerate(kinds)]
    sysm = System(blocks)
    if group != "none":
        _add_effect(sysm, group, rng)
    return _case(sysm, seed, n, dt, noise)


def _add_effect(sysm: System, group: str, rng: np.random.Generator) -> None:
    table = {"in": IN_LIBRARY, "out": OUT_OF_LIBRARY, "beyond": BEYOND}[group]
    options = [(b, e) for b in sysm.blocks for e in table.get(b.kind, ())] + \
              [(None, e) for e in table["any"]]
    blk, effect = options[int(rng.integers(len(options)))]
    sysm.effect = effect
    if effect in ("output_offset", "output_gain"):
        out = sysm.blocks[-1].measured
        size = float(rng.uniform(0.1, 0.3))
        sysm.sensor = (out, effect.split("_")[1], size)
        sysm.equation = out
        return
    if effect == "parameter_drift":
        blk = sysm.blocks[int(rng.integers(len(sysm.blocks)))]
        name = next(iter(blk.params))
        sysm.drift = (name, float(rng.uniform(0.004, 0.008)))   # 20-40 % over a 50 s record
        sysm.equation = blk.states[-1]
        return
    if effect == "dead_zone":
        # a third to a half of the held levels (0.2-2) inside the band: narrower, the input is merely
        # shifted where it is outside it, and a constant source is the same law on these data
        sysm.dead_zone = float(rng.uniform(0.7, 1.0))
        sysm.equation = sysm.blocks[0].states[-1]
        return
    if effect == "knee":
        sysm.knee = float(rng.uniform(0.8, 1.2))   # a third to a half of the held levels above it
        sysm.equation = sysm.blocks[0].states[-1]
        return
    assert blk is not None
    eq = blk.states[-1]
    size = float(rng.uniform(0.3, 0.6))
    terms = {
        "coulomb": lambda x, d, t: -size * np.tanh(x[1] / 1e-3),
        "quadratic_drag": lambda x, d, t: -size * x[1] * abs(x[1]),
        "cubic_stiffness": lambda x, d, t: -size * 4 * x[0] ** 3,
        "offset": lambda x, d, t: size,
        "sqrt_flow": lambda x, d, t: -size * np.sqrt(max(x[0], 0.0)),
        "thrust": lambda x, d, t: 0.5 * d * abs(d),
        "monod": lambda x, d, t: -2 * size * max(x[0], 0.0) / (0.3 + max(x[0], 0.0)),
        "hill": lambda x, d, t: -2 * size * max(x[0], 0.0) ** 2 / (0.5 ** 2 + max(x[0], 0.0) ** 2),
    }
    blk.extra, blk.extra_state = terms[effect], eq
    sysm.equation = eq


def _inputs(rng: np.random.Generator, n: int) -> np.ndarray:
    """Held random levels, each for 20-60 samples, positive for the tanks' and reactors' sake."""
    u = np.empty(n)
    k = 0
    while k < n:
        m = int(rng.integers(20, 61))
        u[k:k + m] = rng.uniform(0.2, 2.0)
        k += m
    return u


def _simulate(sysm: System, t: np.ndarray, u: np.ndarray, x0: np.ndarray) -> np.ndarray:
    sizes = [len(b.states) for b in sysm.blocks]

    def rhs(tt, s, uu):
        out, k, drive = [], 0, _knee(_dead(uu, sysm.dead_zone), sysm.knee)
        for b, m in zip(sysm.blocks, sizes):
            xb = s[k:k + m]
            out += _rhs_block(b, xb, drive, tt, sysm)
            drive, k = xb[0], k + m
        return out
    return simulate(rhs, t, list(x0), u, True)


def _record(sysm: System, name: str, t: np.ndarray, u: np.ndarray, x0: np.ndarray, noise: str, seed: int):
    x = _simulate(sysm, t, u, x0)
    names = [s for b in sysm.blocks for s in b.states]
    outputs = {}
    for b in sysm.blocks:
        y = x[names.index(b.measured)]
        if sysm.sensor is not None and sysm.sensor[0] == b.measured:
            if sysm.sensor[1] == "offset":
                sysm.offset = sysm.sensor[2] * float(np.std(y)) * 5 if sysm.offset is None else sysm.offset
                y = y + sysm.offset
            else:
                y = y * (1 + sysm.sensor[2])
        outputs[b.measured] = noisy(y, noise, seed + len(outputs))
    return {"name": name, "time": t.tolist(), "inputs": {"u": u.tolist()}, "outputs": outputs}, x[:, -1]


def _case(sysm: System, seed: int, n: int, dt: float, noise: str) -> Case:
    rng = np.random.default_rng(10_000 + seed)
    names = [s for b in sysm.blocks for s in b.states]
    t = np.arange(n) * dt
    est, x_end = _record(sysm, "est", t, _inputs(rng, n), np.zeros(len(names)), noise, 20_000 + seed)
    val, _ = _record(sysm, "val", t + n * dt, _inputs(rng, n), x_end, noise, 30_000 + seed)
    equations, drive = {}, "u"
    for b in sysm.blocks:
        equations.update({s: e.format(d=drive) for s, e in b.equations.items()})
        drive = b.states[0]
    truth = {k: v for b in sysm.blocks for k, v in b.params.items()}
    if sysm.drift is not None:   # a drift is written p + d·(t − t̄): p is the value at the record's mean time
        truth[sysm.drift[0]] *= 1 + sysm.drift[1] * float(np.mean(t))
    params = [{"name": k, "value": v * 1.3, "lower": 0.0, "upper": 50.0} for k, v in truth.items()]
    model = {"name": "generated", "states": names, "inputs": ["u"], "parameters": params,
             "equations": equations, "outputs": {b.measured: b.measured for b in sysm.blocks}}
    body = {"model": model, "experiments": [est], "validation": [val], "method": "multiple_shooting",
            "options": {"input_interpolation": "zoh"}}
    return Case(body, truth, sysm.effect, sysm.equation)


def describe(case: Case) -> str:
    """A one-line description of a generated problem, for the bench's log."""
    m = case.body["model"]
    states = ", ".join(m["states"])
    return f"{len(m['states'])} states ({states}), missing {case.effect or 'nothing'} on {case.equation}"
