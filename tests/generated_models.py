"""A procedural generator of grey-box models and their records: mechanical, electrical, thermal, fluid,
chemical and biological blocks of 2–5 states, each with an effect the declared model lacks.

`generate(kind, seed)` draws the block's size and parameters; `record(case, seed)` simulates the true
model (the declared one with the missing effect) with scipy from greyfit's compiled right-hand side,
adds white noise of 1 % of each output's spread, and returns an experiment. Used by the respelling
test and bench (tests/respell.py): what matters there is that every spelling of a model is treated
alike, so the truth may be simulated by greyfit's own compiler.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.integrate import solve_ivp

from greyfit.schemas.model import Model
from greyfit.solvers.model.compiler import compile_model

KINDS = ("mechanical", "electrical", "thermal", "fluid", "chemical", "biological")


@dataclass
class Case:
    kind: str
    model: dict                      # the declared model (parameters start at the truth)
    truth: dict[str, float]          # every parameter of the true model, the missing effect's too
    missing: dict[str, str]          # state -> its true equation, where it differs from the declared one
    x0: list[float]
    inputs: dict[str, tuple[float, float]] = field(default_factory=dict)   # input -> (level, amplitude)


def _model(name: str, states: list[str], inputs: list[str], params: dict[str, float], equations: dict[str, str],
           constants: dict[str, float], measured: list[str]) -> dict:
    return {"name": name, "states": states, "inputs": inputs, "constants": constants,
            "parameters": [{"name": k, "value": v, "lower": 0.0} for k, v in params.items()],
            "equations": equations, "outputs": {f"y_{s}": s for s in measured}}


def _mechanical(rng) -> Case:
    bodies = int(rng.integers(1, 3))
    p = {"k1": rng.uniform(2, 6), "c1": rng.uniform(0.3, 1.0)}
    c = {"m1": 1.0}
    eqs = {"z1": "v1", "v1": "(F - k1*z1 - c1*v1 - {c12})/m1"}
    if bodies == 1:
        eqs["v1"] = eqs["v1"].replace(" - {c12}", "")
        missing = {"v1": eqs["v1"][:-4] + " - cd*v1*abs(v1))/m1"}
        extra = {"cd": rng.uniform(0.5, 1.5)}
    else:
        p.update(k2=rng.uniform(3, 8), c2=rng.uniform(0.2, 0.6))
        c["m2"] = rng.uniform(0.5, 1.5)
        eqs["v1"] = eqs["v1"].format(c12="k2*(z1 - z2) - c2*(v1 - v2)")
        eqs.update(z2="v2", v2="(k2*(z1 - z2) + c2*(v1 - v2))/m2")
        missing = {"v1": eqs["v1"][:-4] + " - k3*(z1 - z2)^3)/m1", "v2": eqs["v2"][:-4] + " + k3*(z1 - z2)^3)/m2"}
        extra = {"k3": rng.uniform(20, 60)}
    states = [s for s in ("z1", "v1", "z2", "v2") if s in eqs]
    model = _model("mech", states, ["F"], p, eqs, c, [s for s in states if s.startswith("z")])
    return Case("mechanical", model, {**p, **extra}, missing, [0.1] + [0.0] * (len(states) - 1), {"F": (0.0, 1.0)})


def _electrical(rng) -> Case:
    caps = int(rng.integers(1, 4))
    p = {f"R{i}": rng.uniform(0.5, 2.0) for i in range(caps + 1)}
    c = {"L": 0.5, **{f"C{i}": rng.uniform(0.5, 1.5) for i in range(1, caps + 1)}}
    eqs = {"iL": "(u - R0*iL - vC1)/L"}
    for i in range(1, caps + 1):
        into = "iL" if i == 1 else f"(vC{i - 1} - vC{i})/R{i - 1}"
        out = f" - (vC{i} - vC{i + 1})/R{i}" if i < caps else f" - vC{i}/R{i}"
        eqs[f"vC{i}"] = f"({into}{out})/C{i}"
    states = list(eqs)
    missing = {"vC1": eqs["vC1"][:-4] + " - g3*vC1^3)/C1"}
    model = _model("rc", states, ["u"], p, eqs, c, [states[-1], "iL"])
    return Case("electrical", model, {**p, "g3": rng.uniform(0.2, 0.5)}, missing, [0.0] * len(states),
                {"u": (1.0, 1.0)})


def _thermal(rng) -> Case:
    nodes = int(rng.integers(2, 5))
    p = {"P": rng.uniform(40, 80), **{f"U{i}": rng.uniform(0.5, 2.0) for i in range(1, nodes + 1)},
         **{f"G{i}": rng.uniform(1.0, 4.0) for i in range(1, nodes)}}
    c = {"Ta": 295.0, **{f"Cp{i}": rng.uniform(5, 15) for i in range(1, nodes + 1)}}
    eqs = {}
    for i in range(1, nodes + 1):
        terms = ["P*u"] if i == 1 else [f"G{i - 1}*(T{i - 1} - T{i})"]
        terms.append(f"- U{i}*(T{i} - Ta)")
        if i < nodes:
            terms.append(f"- G{i}*(T{i} - T{i + 1})")
        eqs[f"T{i}"] = f"({' '.join(terms)})/Cp{i}"
    states = list(eqs)
    missing = {"T1": eqs["T1"][:-5] + " + P2*u^2)/Cp1"}
    model = _model("heat", states, ["u"], p, eqs, c, states[:2])
    return Case("thermal", model, {**p, "P2": 0.5 * p["P"]}, missing, [300.0] * nodes, {"u": (0.5, 0.4)})


def _fluid(rng) -> Case:
    tanks = int(rng.integers(2, 6))
    # the last tank drains to a level h0 (a parameter on one side of a difference)
    p = {"b": rng.uniform(0.5, 1.5), "h0": 0.1, **{f"a{i}": rng.uniform(0.3, 1.0) for i in range(1, tanks + 1)}}
    c = {f"A{i}": rng.uniform(0.5, 2.0) for i in range(1, tanks + 1)}
    eqs = {f"h{i}": (f"(b*q - a{i}*h{i})/A{i}" if i == 1 else f"(a{i - 1}*h{i - 1} - a{i}*h{i})/A{i}")
           for i in range(1, tanks + 1)}
    eqs[f"h{tanks}"] = eqs[f"h{tanks}"].replace(f"a{tanks}*h{tanks}", f"a{tanks}*(h{tanks} - h0)")
    states = list(eqs)
    missing = {"h1": eqs["h1"][:-4] + " - bq*q*h1)/A1"}
    model = _model("tanks", states, ["q"], p, eqs, c, [states[-1], states[0]])
    return Case("fluid", model, {**p, "bq": 0.2 * p["b"]}, missing, [0.5] * tanks, {"q": (1.0, 0.5)})


def _chemical(rng) -> Case:
    reactors = int(rng.integers(2, 5))
    p = {"D": rng.uniform(0.3, 0.8), **{f"k{i}": rng.uniform(0.1, 0.5) for i in range(1, reactors + 1)}}
    eqs = {f"C{i}": (f"D*(Cin - C{i}) - k{i}*C{i}" if i == 1 else f"D*(C{i - 1} - C{i}) - k{i}*C{i}")
           for i in range(1, reactors + 1)}
    states = list(eqs)
    missing = {"C1": eqs["C1"] + " - k1b*C1^2"}
    model = _model("cstr", states, ["Cin"], p, eqs, {}, states[:2])
    return Case("chemical", model, {**p, "k1b": 0.3}, missing, [0.2] * reactors, {"Cin": (2.0, 1.0)})


def _biological(rng) -> Case:
    comps = int(rng.integers(2, 5))
    p = {"ka": rng.uniform(0.5, 1.0), "ke": rng.uniform(0.1, 0.3),
         **{f"k{i}{j}": rng.uniform(0.1, 0.4) for i in range(2, comps) for j in (i + 1,)},
         **{f"k{j}{i}": rng.uniform(0.1, 0.4) for i in range(2, comps) for j in (i + 1,)}}
    eqs = {"A1": "dose - ka*A1", "A2": "ka*A1 - ke*A2"}
    for i in range(2, comps):
        eqs[f"A{i}"] += f" - k{i}{i + 1}*A{i} + k{i + 1}{i}*A{i + 1}"
        eqs[f"A{i + 1}"] = f"k{i}{i + 1}*A{i} - k{i + 1}{i}*A{i + 1}"
    states = list(eqs)
    missing = {"A2": eqs["A2"] + " - Vm*A2/(Km + A2)"}
    model = _model("pk", states, ["dose"], p, eqs, {}, ["A2", "A1"])
    return Case("biological", model, {**p, "Vm": 0.3, "Km": 1.0}, missing, [0.0] * comps, {"dose": (1.0, 0.8)})


BLOCKS = {"mechanical": _mechanical, "electrical": _electrical, "thermal": _thermal, "fluid": _fluid,
          "chemical": _chemical, "biological": _biological}


def generate(kind: str, seed: int) -> Case:
    """A random block of `kind` (see `KINDS`), its size and parameters drawn from `seed`."""
    return BLOCKS[kind](np.random.default_rng(seed))


def true_model(case: Case) -> Model:
    """The declared model with the missing effect's equations and parameters."""
    body = dict(case.model)
    body["equations"] = {**case.model["equations"], **case.missing}
    body["parameters"] = [{"name": k, "value": v} for k, v in case.truth.items()]
    return Model.model_validate(body)


def _input(t: np.ndarray, level: float, amplitude: float, rng) -> np.ndarray:
    """A sum of three sines and a few held steps around `level`, kept non-negative where `level` > 0."""
    f = rng.uniform(0.05, 0.5, 3)
    u = level + 0.4 * amplitude * sum(np.sin(2 * np.pi * fi * t + rng.uniform(0, 6)) for fi in f)
    steps = np.repeat(rng.uniform(-0.6, 0.6, 6), int(np.ceil(t.size / 6)))[:t.size]
    u = u + amplitude * steps
    return np.maximum(u, 0.0) if level > 0 else u


def record(case: Case, seed: int, n: int = 300, dt: float = 0.1, name: str = "e1") -> dict:
    """An experiment of the true model: inputs drawn from `seed`, outputs with 1 % white noise."""
    rng = np.random.default_rng(seed)
    cm = compile_model(true_model(case))
    t = np.arange(n) * dt
    u = np.array([_input(t, *case.inputs[k], rng) for k in cm.inputs])
    p = np.array([case.truth[k] for k in cm.parameters])

    def rhs(tt, x):
        uu = [np.interp(tt, t, row) for row in u]
        return np.asarray(cm.rhs(x, uu, p, tt)).ravel()
    sol = solve_ivp(rhs, (0, t[-1]), case.x0, t_eval=t, method="LSODA", rtol=1e-8, atol=1e-10, max_step=dt)
    x = sol.y if sol.success and sol.y.shape[1] == n else np.zeros((len(cm.states), n))
    y = np.array([np.asarray(cm.output(x[:, i], u[:, i], p, t[i])).ravel() for i in range(n)]).T
    spread = np.ptp(y, axis=1, keepdims=True) + 1e-9
    y = y + 0.01 * spread * rng.standard_normal(y.shape)
    return {"name": name, "time": t.tolist(), "inputs": {k: u[j].tolist() for j, k in enumerate(cm.inputs)},
            "outputs": {k: y[j].tolist() for j, k in enumerate(cm.outputs)},
            "initial_state": dict(zip(cm.states, case.x0))}
