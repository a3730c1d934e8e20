"""Units of parameters without one, by dimensional analysis of the equations they enter.

A parameter that discovery adds (a cubic spring's k3 in ``dv/dt = (u - c*v - k*x - k3*x^3)/m``)
has no declared unit; its unit follows from the equation's: every term of ``dv/dt`` has the unit of
``v`` over that of ``t``, so ``k3 x^3 / m`` is in m/s², and with ``m`` in kg and ``x`` in m, k3 is in
kg/(m² s²). Units are products of powers of symbols (``"N s/m"`` is N¹ s¹ m⁻¹), compared as such
(no conversion between N and kg m/s²: a unit is what the model declares). Where anything is not
known (a name without a unit, a unit that does not read, terms that disagree) no unit is inferred.
"""
from __future__ import annotations

import re
from fractions import Fraction
from typing import Optional

from greyfit.schemas.model import Model
from greyfit.solvers.errors import ModelDefinitionError
from greyfit.solvers.model.expressions import Node, parse

Unit = dict[str, Fraction]      # symbol -> exponent; {} is dimensionless
UNKNOWN = "\0"                  # the exponent of the parameter whose unit is sought
_SYMBOL = re.compile(r"^([^\W\d_][\w°Ωµ]*)(?:\^|\*\*)?(-?\d+(?:/\d+)?)?$")
_SAME = ("abs", "min", "max")   # functions whose value has their argument's unit
_ROOTS = {"sqrt": Fraction(1, 2)}


class _Unknowable(Exception):
    pass


def read_unit(text: str) -> Optional[Unit]:
    """``{"N": 1, "s": 1, "m": -1}`` for ``"N s/m"`` (``*`` or a space multiply; what follows ``/``
    divides; ``^2``, ``**2`` or ``2`` after a symbol is a power; ``1`` is dimensionless); None where
    it does not read.

    Parameters
    ----------
    text : str
        The unit as written.

    Returns
    -------
    Unit or None
        The exponents by symbol.
    """
    out: Unit = {}
    numerator, _, denominator = text.replace("·", " ").replace("**", "^").partition("/")
    for part, sign in ((numerator, 1), (denominator, -1)):
        for token in part.replace("*", " ").replace("(", " ").replace(")", " ").split():
            if token == "1":
                continue
            match = _SYMBOL.match(token)
            if match is None:
                return None
            power = Fraction(match.group(2) or 1) * sign
            out[match.group(1)] = out.get(match.group(1), Fraction(0)) + power
    return {k: v for k, v in out.items() if v}


def write_unit(unit: Unit) -> str:
    """``"kg/(m^2 s^2)"``-style text of a unit (``"1"`` when dimensionless).

    Parameters
    ----------
    unit : Unit
        Exponents by symbol.

    Returns
    -------
    str
        The unit as text.
    """
    def power(symbol: str, exponent: Fraction) -> str:
        return symbol if exponent == 1 else f"{symbol}^{exponent}"
    up = " ".join(power(s, e) for s, e in sorted(unit.items()) if e > 0)
    down = [power(s, -e) for s, e in sorted(unit.items()) if e < 0]
    if not down:
        return up or "1"
    below = down[0] if len(down) == 1 else f"({' '.join(down)})"
    return f"{up or '1'}/{below}"


def _combine(a: Unit, b: Unit, sign: int) -> Unit:
    out = dict(a)
    for k, v in b.items():
        out[k] = out.get(k, Fraction(0)) + sign * v
    return {k: v for k, v in out.items() if v}


def _scale(a: Unit, factor: Fraction) -> Unit:
    return {k: v * factor for k, v in a.items() if v * factor}


class _Analysis:
    """Walks one expression; `solved` is the sought parameter's unit once an equality fixed it. A
    name without a unit makes what holds it undetermined (None), which fixes nothing."""

    def __init__(self, known: dict[str, Unit], unknown: str):
        self.known, self.unknown = known, unknown
        self.solved: Optional[Unit] = None

    def unit(self, node: Node) -> Optional[Unit]:
        kind = node[0]
        if kind == "num":
            return {}
        if kind == "name":
            return self._name(node[1])
        if kind == "neg":
            return self.unit(node[1])
        if kind == "bin":
            return self._binary(node[1], node[2], node[3])
        if kind == "call":
            return self._call(node[1], node[2])
        return None   # comparisons: a switch, no unit of its own

    def _name(self, name: str) -> Optional[Unit]:
        if name == self.unknown:
            return dict(self.solved) if self.solved is not None else {UNKNOWN: Fraction(1)}
        return self.known.get(name)

    def _binary(self, op: str, left: Node, right: Node) -> Optional[Unit]:
        a, b = self.unit(left), self.unit(right)
        if op in ("+", "-"):
            return self.equate(a, b)
        if op in ("*", "/"):
            return None if a is None or b is None else _combine(a, b, 1 if op == "*" else -1)
        exponent = _number(right)
        if exponent is not None:
            return None if a is None else _scale(a, Fraction(exponent).limit_denominator(12))
        self.equate(b, {})
        return self.equate(a, {})

    def _call(self, name: str, args: tuple) -> Optional[Unit]:
        units = [self.unit(a) for a in args]
        if name in _SAME:
            first = units[0]
            for other in units[1:]:
                first = self.equate(first, other)
            return first
        if name in _ROOTS:
            return None if units[0] is None else _scale(units[0], _ROOTS[name])
        for u in units:            # sin, exp, tanh, sign, atan2...: arguments without a unit
            self.equate(u, {})
        return {}

    def equate(self, a: Optional[Unit], b: Optional[Unit]) -> Optional[Unit]:
        """a and b must be equal; solve for the sought parameter where one side holds it."""
        if a is None or b is None:
            return b if a is None else a
        ka, kb = a.get(UNKNOWN, Fraction(0)), b.get(UNKNOWN, Fraction(0))
        rest_a = {k: v for k, v in a.items() if k != UNKNOWN}
        rest_b = {k: v for k, v in b.items() if k != UNKNOWN}
        if ka == kb:
            if rest_a != rest_b:
                raise _Unknowable("the terms' units differ")
            return a
        self.solved = _scale(_combine(rest_b, rest_a, -1), 1 / (ka - kb))
        return _combine(rest_a, _scale(self.solved, ka), 1)


def _number(node: Node) -> Optional[float]:
    if node[0] == "num":
        return float(node[1])
    if node[0] == "neg" and node[1][0] == "num":
        return -float(node[1][1])
    return None


def parameter_units(model: Model) -> dict[str, str]:
    """Units the state equations imply for the model's parameters that declare none.

    Parameters
    ----------
    model : Model
        The model; its `units` (states, inputs, outputs, ``t``) and its parameters' units are read.

    Returns
    -------
    dict of str to str
        Parameter name -> unit as text (``"1"`` for a dimensionless one), for each parameter whose
        unit the equations fix; one found helps find the next (a Coulomb force's level from its
        smoothing width), until none is added.
    """
    known = {k: u for k, text in model.units.items() if (u := read_unit(text)) is not None}
    known.update({p.name: u for p in model.parameters if p.unit and (u := read_unit(p.unit)) is not None})
    missing = [p.name for p in model.parameters if p.name not in known]
    found: dict[str, str] = {}
    while missing:
        new = {n: u for n in missing if (u := _solve(model, known, n)) is not None}
        if not new:
            break
        known.update(new)
        found.update({n: write_unit(u) for n, u in new.items()})
        missing = [n for n in missing if n not in new]
    return found


def _solve(model: Model, known: dict[str, Unit], name: str) -> Optional[Unit]:
    """`name`'s unit from the first state equation that fixes it: inside the right-hand side (its
    terms, the arguments of its functions), else by the right-hand side's unit, the state's over t's."""
    for state, text in model.equations.items():
        analysis = _Analysis(known, name)
        try:
            rhs = analysis.unit(parse(text, f"equations.{state}"))
            if analysis.solved is None and state in known and "t" in known:
                analysis.equate(rhs, _combine(known[state], known["t"], -1))
        except (_Unknowable, ModelDefinitionError, ZeroDivisionError):
            continue
        if analysis.solved is not None:
            return analysis.solved
    return None
