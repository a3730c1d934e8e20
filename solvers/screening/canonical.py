"""The model's equations by what they mean, not how they are spelled: the form candidates are built on.

Every state equation (definitions inlined) is compiled to CasADi with the states, inputs, parameters,
constants and time as symbols, and expanded into a sum of monomials: sums, differences and negations
split, products distributed over sums, a quotient's numerator split over its denominator. A monomial
linear in one state or input (its coefficient, `ca.jacobian`, free of every variable) or, when it holds
no state or input, linear in one constant (a level such as an ambient temperature) is a *linear part*.
Two linear parts of one equation whose coefficients cancel, checked at random values of the
parameters and constants so that an identity is not taken for a coincidence, are a *coupling*: the
difference a − b the equation acts on. `U*A*(Ta - T)`, `-U*A*(T - Ta)`, `U*A*Ta - U*A*T` and
`(Ta - T)/(1/(U*A))` all give the coupling (T, Ta) in dT/dt, oriented the same way.

A kinematic identity dx/dt = v is an equation that is one linear part of another state with
coefficient 1 (`v`, `1*v`, `--v`, `(2*v)/2` alike).
"""
from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import casadi as ca
import numpy as np

from greyfit.schemas.model import Model
from greyfit.solvers.model.expressions import compile_expression

MAX_MONOMIALS = 256   # a product of sums expanded beyond this is kept whole (no law is found inside it)
DRAWS = 4             # random values of the parameters and constants an identity is checked at
TOLERANCE = 1e-9      # relative: coefficients that cancel to this are an identity
_CACHE: OrderedDict[str, "CanonicalForm"] = OrderedDict()
CACHE_SIZE = 32


@dataclass(frozen=True)
class Coupling:
    """A difference a − b an equation acts on linearly (a spring, a damper, a heat exchange).

    `a` is the equation's own state when the pair holds it, else the pair's first state in model
    order; `b` is the other (a state, an input or a constant). `scales` are the parameters the
    coupling's coefficient is proportional to (a stiffness, a conductance; not a mass it is divided by).
    """

    equation: str
    a: str
    b: str
    scales: tuple[str, ...]


@dataclass(frozen=True)
class CanonicalForm:
    """The couplings of every state equation, and the kinematic identities (velocity -> position)."""

    couplings: tuple[Coupling, ...]
    pos_of: dict[str, str]     # velocity -> its position (dx/dt = v)
    vel_of: dict[str, str]     # position -> its velocity
    # parameter -> the names of its linear parts, for parameters every monomial of which (in every
    # equation) is a linear part: a ks used only in ks*(zs - zu) gives {zs, zu}
    linear_in: dict[str, frozenset[str]]
    # state -> the parameters and constants every monomial of its equation is divided by (a mass, a
    # heat capacity): a new term is divided by them too, so its parameter is a force, whatever the spelling
    divisors: dict[str, tuple[str, ...]]


def expand(e: ca.SX) -> list[ca.SX]:
    """The monomials of a scalar expression: sums split, products distributed, numerators split.

    Parameters
    ----------
    e : casadi.SX
        A scalar expression.

    Returns
    -------
    list of casadi.SX
        Terms whose sum is `e`; a product whose expansion would pass `MAX_MONOMIALS` terms stays whole.
    """
    op = e.op()
    if op in (ca.OP_ADD, ca.OP_SUB):
        right = expand(e.dep(1))
        return expand(e.dep(0)) + (right if op == ca.OP_ADD else [-t for t in right])
    if op == ca.OP_NEG:
        return [-t for t in expand(e.dep(0))]
    if op == ca.OP_TWICE:   # CasADi's own node for 2*x
        return [2 * t for t in expand(e.dep(0))]
    if op == ca.OP_MUL:
        left, right = expand(e.dep(0)), expand(e.dep(1))
        if len(left) * len(right) > MAX_MONOMIALS:
            return [e]
        return [a * b for a in left for b in right]
    if op == ca.OP_DIV:
        return [t / e.dep(1) for t in expand(e.dep(0))]
    return [e]


class _Symbols:
    """The model compiled with every name a symbol: variables (states, inputs, t) and coefficients
    (parameters, constants), and the equations (definitions inlined)."""

    def __init__(self, model: Model):
        self.model = model
        self.variables = {n: ca.SX.sym(n) for n in [*model.states, *model.inputs]}
        self.constants = {n: ca.SX.sym(n) for n in model.constants}
        self.parameters = {p.name: ca.SX.sym(p.name) for p in model.parameters}
        self.t = ca.SX.sym("t")
        env: dict[str, object] = {"t": self.t, **self.variables, **self.constants, **self.parameters}
        for name, text in model.definitions.items():
            env[name] = compile_expression(text, env, f"definitions.{name}")
        self.equations = {s: ca.SX(compile_expression(model.equations[s], env, f"equations.{s}"))
                          for s in model.states}
        self.moving = ca.vertcat(self.t, *self.variables.values())
        self.coefficients = ca.vertcat(*self.parameters.values(), *self.constants.values())
        rng = np.random.default_rng(0)
        self.draws = rng.uniform(0.5, 2.0, size=(DRAWS, self.coefficients.numel()))

    def linear_parts(self, m: ca.SX) -> list[tuple[str, ca.SX]]:
        """(name, coefficient) of a monomial linear in one variable, or in one constant when it holds no variable."""
        used = [n for n, s in self.variables.items() if ca.depends_on(m, s)]
        if len(used) == 1:
            c = ca.jacobian(m, self.variables[used[0]])
            return [] if ca.depends_on(c, self.moving) else [(used[0], c)]
        if used or ca.depends_on(m, self.t):
            return []
        out = []
        for n, s in self.constants.items():
            if ca.depends_on(m, s):
                c = ca.jacobian(m, s)
                if not ca.depends_on(c, s):
                    out.append((n, c))
        return out

    def values(self, coefficients: list[ca.SX]) -> np.ndarray:
        """(DRAWS, len(coefficients)) values of parameter-and-constant expressions at the random draws."""
        if not coefficients:
            return np.zeros((DRAWS, 0))
        fn = ca.Function("c", [self.coefficients], [ca.vertcat(*coefficients)])
        return np.column_stack([np.asarray(fn(d)).ravel() for d in self.draws]).T

    def scales(self, c: ca.SX) -> tuple[str, ...]:
        """Parameters p the coefficient c is proportional to: p·∂c/∂p ≡ c."""
        out = []
        for n, s in self.parameters.items():
            if ca.depends_on(c, s):
                v = self.values([s * ca.jacobian(c, s), c])
                if np.allclose(v[:, 0], v[:, 1], rtol=TOLERANCE, atol=0.0):
                    out.append(n)
        return tuple(out)


def _groups(sym: _Symbols, s: str) -> list[tuple[str, ca.SX]]:
    """The linear parts of equation s, summed per (name, the coefficient's symbols): -(d1 + d2)*v2
    gives two groups, -d1*v2 and -d2*v2, to pair with d1*v1 and d2*v3."""
    groups: dict[tuple[str, tuple[str, ...]], ca.SX] = {}
    names = [*sym.parameters, *sym.constants]
    for m in expand(sym.equations[s]):
        for name, c in sym.linear_parts(m):
            key = (name, tuple(n for n in names if ca.depends_on(c, _symbol(sym, n))))
            groups[key] = groups[key] + c if key in groups else c
    return [(name, c) for (name, _), c in groups.items()]


def _symbol(sym: _Symbols, n: str) -> ca.SX:
    return sym.parameters[n] if n in sym.parameters else sym.constants[n]


def _orient(model: Model, eq: str, x: str, y: str) -> tuple[str, str] | None:
    """(a, b): the equation's own state first, else a state before an input before a constant; None
    without a state."""
    order = [*model.states, *model.inputs, *model.constants]
    if eq in (x, y):
        return (eq, y if x == eq else x)
    if x not in model.states and y not in model.states:
        return None
    return (x, y) if order.index(x) < order.index(y) else (y, x)


def _couplings(sym: _Symbols, s: str) -> list[Coupling]:
    groups = _groups(sym, s)
    vals = sym.values([c for _, c in groups])
    out: list[Coupling] = []
    for i, (x, cx) in enumerate(groups):
        for j in range(i + 1, len(groups)):
            y = groups[j][0]
            size = np.abs(vals[:, i]) + np.abs(vals[:, j])
            if x == y or not np.all(np.isfinite(size)) or np.any(size == 0):
                continue
            if np.all(np.abs(vals[:, i] + vals[:, j]) <= TOLERANCE * size):
                ab = _orient(sym.model, s, x, y)
                if ab is not None:
                    out.append(Coupling(s, ab[0], ab[1], sym.scales(cx)))
    return out


def _kinematic(sym: _Symbols, s: str) -> str | None:
    """The state v when d(s)/dt is exactly v (coefficient 1 at every draw), else None."""
    terms = expand(sym.equations[s])
    parts = sym.linear_parts(terms[0]) if len(terms) == 1 else []
    if len(parts) != 1 or parts[0][0] not in sym.model.states or parts[0][0] == s:
        return None
    return parts[0][0] if np.allclose(sym.values([parts[0][1]]), 1.0, rtol=TOLERANCE, atol=0.0) else None


def _linear_in(sym: _Symbols) -> dict[str, frozenset[str]]:
    """Parameter -> the names its monomials are linear parts in, where all of them are."""
    seen: dict[str, set[str]] = {n: set() for n in sym.parameters}
    for s in sym.model.states:
        for m in expand(sym.equations[s]):
            for n in [n for n in seen if ca.depends_on(m, sym.parameters[n])]:
                parts = sym.linear_parts(m)
                if parts:
                    seen[n] |= {name for name, _ in parts}
                else:
                    del seen[n]
    return {n: frozenset(names) for n, names in seen.items() if names}


def _divisors(sym: _Symbols, s: str) -> tuple[str, ...]:
    """Parameters and constants c with every monomial m of equation s ∝ 1/c (c·∂m/∂c ≡ −m)."""
    terms = [m for m in expand(sym.equations[s]) if not m.is_constant()]
    names = {**sym.parameters, **sym.constants}
    found = [n for n, c in names.items() if terms and all(ca.depends_on(m, c) for m in terms)]
    if not found:
        return ()
    everything = ca.vertcat(sym.coefficients, sym.moving)
    rng = np.random.default_rng(1)
    out = []
    for n in found:
        c = names[n]
        fn = ca.Function("d", [everything], [ca.vertcat(*[c * ca.jacobian(m, c) + m for m in terms]),
                                             ca.vertcat(*terms)])
        ok = True
        for _ in range(DRAWS):
            gap, size = (np.asarray(v).ravel() for v in fn(rng.uniform(0.5, 2.0, everything.numel())))
            ok = ok and bool(np.all(np.abs(gap) <= 1e-9 * np.maximum(np.abs(size), 1e-300)))
        if ok:
            out.append(n)
    return tuple(out)


def canonical_form(model: Model) -> CanonicalForm:
    """The couplings and kinematic identities of the model, the same for every spelling of it.

    Parameters
    ----------
    model : Model
        The model (its equations and definitions are compiled; outputs are not read).

    Returns
    -------
    CanonicalForm
        Couplings in model order of the equations (each pair once per equation, distinct), and the
        kinematic identities.

    Raises
    ------
    ModelDefinitionError
        When an equation or definition does not parse or uses an unknown name.
    """
    key = model.model_dump_json()
    if key in _CACHE:
        _CACHE.move_to_end(key)
        return _CACHE[key]
    sym = _Symbols(model)
    found: dict[tuple[str, str, str], tuple[str, ...]] = {}
    pos_of: dict[str, str] = {}
    for s in model.states:
        for c in _couplings(sym, s):   # one pair twice in an equation (two dampers in parallel): one coupling
            scales = found.get((c.equation, c.a, c.b), ())
            found[(c.equation, c.a, c.b)] = scales + tuple(p for p in c.scales if p not in scales)
        v = _kinematic(sym, s)
        if v is not None:
            pos_of[v] = s
    form = CanonicalForm(tuple(Coupling(*k, v) for k, v in found.items()), pos_of, {x: v for v, x in pos_of.items()},
                         _linear_in(sym), {s: _divisors(sym, s) for s in model.states})
    _CACHE[key] = form
    while len(_CACHE) > CACHE_SIZE:
        _CACHE.popitem(last=False)
    return form
