"""Whitelist expression grammar compiled to CasADi; user text is never passed to eval.

Grammar (precedence low to high)::

    expr    := sum [cmp sum]            cmp: < <= > >= == !=
    sum     := product (("+"|"-") product)*
    product := unary (("*"|"/") unary)*
    unary   := "-" unary | "+" unary | power
    power   := atom [("^"|"**") unary]  (right associative)
    atom    := number | name | name "(" args ")" | "(" expr ")"
"""
from __future__ import annotations

import functools
import math
import re
from dataclasses import dataclass
from typing import Callable, Mapping, Union

import casadi as ca

from greyfit.solvers.errors import ModelDefinitionError

MAX_DEPTH = 64
MAX_LENGTH = 4000

_TOKEN = re.compile(
    r"\s*(?:(?P<num>(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?)"
    r"|(?P<name>[A-Za-z_][A-Za-z0-9_]*)"
    r"|(?P<op>\*\*|<=|>=|==|!=|[-+*/^(),<>]))",
    re.ASCII)   # \d and \s must not take Unicode digits (e.g. '١٢') or spaces as numbers and blanks

_UNARY: dict[str, Callable] = {
    "sin": ca.sin, "cos": ca.cos, "tan": ca.tan, "asin": ca.asin, "acos": ca.acos,
    "atan": ca.atan, "sinh": ca.sinh, "cosh": ca.cosh, "tanh": ca.tanh, "exp": ca.exp,
    "log": ca.log, "log10": ca.log10, "sqrt": ca.sqrt, "abs": ca.fabs, "sign": ca.sign,
}
_BINARY: dict[str, Callable] = {
    "atan2": ca.atan2, "min": ca.fmin, "max": ca.fmax, "pow": lambda a, b: a ** b,
}
FUNCTIONS = sorted([*_UNARY, *_BINARY, "if_else"])
CONSTANTS = {"pi": math.pi, "e": math.e}
_COMPARE = {"<", "<=", ">", ">=", "==", "!="}

Node = Union[tuple]


@dataclass
class Token:
    kind: str
    text: str
    column: int


def tokenize(text: str, where: str) -> list[Token]:
    """Split an expression into number, name and operator tokens, ending with an ``end`` token.

    Parameters
    ----------
    text : str
        The expression, at most `MAX_LENGTH` characters.
    where : str
        Field path named in the errors (e.g. ``equations.x``).

    Returns
    -------
    list of Token
        The tokens with their 1-based columns.

    Raises
    ------
    ModelDefinitionError
        When the text is too long or holds a character outside the grammar (the column is named).
    """
    if len(text) > MAX_LENGTH:
        raise ModelDefinitionError(
            f"expression has {len(text)} characters, the limit is {MAX_LENGTH}; split it with definitions",
            where)
    tokens, pos = [], 0
    while pos < len(text):
        if text[pos:].strip() == "":
            break
        m = _TOKEN.match(text, pos)
        if m is None or m.end() == pos:
            col = pos + len(text[pos:]) - len(text[pos:].lstrip()) + 1
            raise ModelDefinitionError(f"unexpected character {text[col - 1]!r} at column {col}", where)
        kind = m.lastgroup or "op"
        tokens.append(Token(kind, m.group(kind), m.start(kind) + 1))
        pos = m.end()
    tokens.append(Token("end", "", len(text) + 1))
    return tokens


class _Parser:
    def __init__(self, text: str, where: str):
        self.where = where
        self.tokens = tokenize(text, where)
        self.i = 0
        self.depth = 0

    def peek(self) -> Token:
        return self.tokens[self.i]

    def take(self) -> Token:
        tok = self.tokens[self.i]
        self.i += 1
        return tok

    def fail(self, msg: str, tok: Token) -> ModelDefinitionError:
        return ModelDefinitionError(f"{msg} at column {tok.column}", self.where)

    def expect(self, text: str) -> Token:
        tok = self.take()
        if tok.text != text:
            got = "end of expression" if tok.kind == "end" else repr(tok.text)
            raise self.fail(f"expected {text!r}, found {got}", tok)
        return tok

    def parse(self) -> Node:
        if self.peek().kind == "end":
            raise self.fail("empty expression", self.peek())
        node = self.expr()
        tok = self.peek()
        if tok.kind != "end":
            raise self.fail(f"unexpected {tok.text!r}", tok)
        return node

    def nest(self, tok: Token) -> None:
        self.depth += 1
        if self.depth > MAX_DEPTH:
            raise self.fail(f"expression nested deeper than {MAX_DEPTH} levels", tok)

    def expr(self) -> Node:
        left = self.sum()
        if self.peek().text in _COMPARE:
            op = self.take().text
            right = self.sum()
            if self.peek().text in _COMPARE:
                raise self.fail("chained comparison; use if_else or separate constraints", self.peek())
            return ("cmp", op, left, right)
        return left

    def sum(self) -> Node:
        node = self.product()
        while self.peek().text in ("+", "-"):
            op = self.take().text
            node = ("bin", op, node, self.product())
        return node

    def product(self) -> Node:
        node = self.unary()
        while self.peek().text in ("*", "/"):
            op = self.take().text
            node = ("bin", op, node, self.unary())
        return node

    def unary(self) -> Node:
        tok = self.peek()
        if tok.text in ("-", "+"):
            self.take()
            self.nest(tok)
            inner = self.unary()
            self.depth -= 1
            return ("neg", inner) if tok.text == "-" else inner
        return self.power()

    def power(self) -> Node:
        base = self.atom()
        if self.peek().text in ("^", "**"):
            tok = self.take()
            self.nest(tok)
            exponent = self.unary()
            self.depth -= 1
            return ("bin", "^", base, exponent)
        return base

    def atom(self) -> Node:
        tok = self.take()
        if tok.kind == "num":
            value = float(tok.text)
            if not math.isfinite(value):
                raise self.fail(f"number {tok.text} is too large for double precision", tok)
            return ("num", value)
        if tok.kind == "name":
            if self.peek().text == "(":
                return self.call(tok)
            return ("name", tok.text, tok.column)
        if tok.text == "(":
            self.nest(tok)
            node = self.expr()
            self.expect(")")
            self.depth -= 1
            return node
        got = "end of expression" if tok.kind == "end" else repr(tok.text)
        raise self.fail(f"expected a number, name or '(', found {got}", tok)

    def call(self, name: Token) -> Node:
        fname = name.text
        if fname not in _UNARY and fname not in _BINARY and fname != "if_else":
            raise self.fail(f"unknown function '{fname}' (allowed: {', '.join(FUNCTIONS)})", name)
        self.expect("(")
        self.nest(name)
        args = [self.expr()]
        while self.peek().text == ",":
            self.take()
            args.append(self.expr())
        self.expect(")")
        self.depth -= 1
        want = 1 if fname in _UNARY else 2 if fname in _BINARY else 3
        if len(args) != want:
            raise self.fail(f"{fname} takes {want} argument(s), got {len(args)}", name)
        return ("call", fname, tuple(args), name.column)


def parse(text: str, where: str) -> Node:
    """Parse `text` into an AST; errors name `where` and the column.

    Parameters
    ----------
    text : str
        The expression, in the grammar of this module.
    where : str
        Field path named in the errors.

    Returns
    -------
    Node
        The AST as nested tuples: ``("num", value)``, ``("name", name, column)``, ``("neg", child)``,
        ``("bin" | "cmp", op, left, right)``, ``("call", function, args, column)``.

    Raises
    ------
    ModelDefinitionError
        On a syntax error, an unknown function, a wrong argument count or nesting beyond `MAX_DEPTH`.
    """
    return _parse(text, where)


# a fit's checks parse the model's equations again (the lack-of-fit screen's catalogue reads each
# equation; ~0.1 ms each on the seat model): the AST is immutable tuples, so one parse serves all
@functools.lru_cache(maxsize=4096)
def _parse(text: str, where: str) -> Node:
    return _Parser(text, where).parse()


def _children(node: Node) -> tuple:
    kind = node[0]
    if kind in ("num", "name"):
        return ()
    if kind == "neg":
        return (node[1],)
    if kind in ("bin", "cmp"):
        return (node[2], node[3])
    return tuple(node[2])


def _postorder(node: Node, combine: Callable):
    """`combine(node, child_results)` bottom-up with an explicit stack.

    Sums and products of many terms parse to left-deep trees (a 1000-term chain is 1000 levels
    deep); walking them recursively would exhaust Python's recursion limit.
    """
    stack: list[tuple[Node, bool]] = [(node, False)]
    results: list = []
    while stack:
        current, expanded = stack.pop()
        kids = _children(current)
        if expanded or not kids:
            k = len(kids)
            args = results[len(results) - k:] if k else []
            if k:
                del results[len(results) - k:]
            results.append(combine(current, args))
        else:
            stack.append((current, True))
            stack.extend((child, False) for child in reversed(kids))
    return results[0]


def names_in(node: Node) -> set[str]:
    """Every name an AST refers to (variables, parameters, constants).

    Parameters
    ----------
    node : Node
        An AST from `parse`.

    Returns
    -------
    set of str
        The names of its ``name`` nodes (function names are not included).
    """
    found: set[str] = set()
    stack = [node]
    while stack:
        current = stack.pop()
        if current[0] == "name":
            found.add(current[1])
        stack.extend(_children(current))
    return found


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _apply(node: Node, args: list):
    """The CasADi operation of one node on already compiled arguments."""
    kind = node[0]
    if kind == "neg":
        return -args[0]
    if kind == "bin":
        a, b = args
        op = node[1]
        if op == "+":
            return a + b
        if op == "-":
            return a - b
        if op == "*":
            return a * b
        if op == "/":
            return a / b
        return a ** b
    if kind == "cmp":
        a, b = args
        return {"<": a < b, "<=": a <= b, ">": a > b, ">=": a >= b,
                "==": a == b, "!=": a != b}[node[1]]
    fname = node[1]
    if fname in _UNARY:
        return _UNARY[fname](args[0])
    if fname in _BINARY:
        return _BINARY[fname](args[0], args[1])
    return ca.if_else(args[0], args[1], args[2])


def _fold(node: Node, args: list, where: str) -> float:
    """Evaluate a node whose arguments are all numbers, in IEEE arithmetic (CasADi DM).

    Python floats raise on 1/0 and 1e308**2 and turn (-1)**0.5 complex; DM gives inf/NaN, which
    is refused here: a constant that is not a finite real number is a modelling error.
    """
    value = float(_apply(node, [ca.DM(a) for a in args]))
    if not math.isfinite(value):
        what = "not a real number" if math.isnan(value) else "infinite"
        raise ModelDefinitionError(
            f"the constant part '{unparse(node)}' is {what} (it evaluates to {value}); "
            "check divisions by zero, overflowing powers and roots of negative numbers", where)
    return value


# Below this argument a root or logarithm is continued by a C¹ polynomial (see `_guarded`)
GUARD_EPSILON = 1e-9


def _root_guard(z, power: float):
    """z^p (0 < p < 1) exact for z ≥ ε; below, A z + B max(z, 0)² with the value and slope of z^p
    at ε and 0 at 0, so the derivative stays finite (A = (2 − p) ε^(p−1)) and z < 0 is no NaN."""
    eps = GUARD_EPSILON
    a, b = (2.0 - power) * eps ** (power - 1.0), (power - 1.0) * eps ** (power - 2.0)
    exact = ca.sqrt(ca.fmax(z, eps)) if power == 0.5 else ca.fmax(z, eps) ** power
    return ca.if_else(z >= eps, exact, a * z + b * ca.fmax(z, 0.0) ** 2)


def _log_guard(z):
    """log z exact for z ≥ ε, its tangent at ε below (finite, no NaN for z ≤ 0)."""
    eps = GUARD_EPSILON
    return ca.if_else(z >= eps, ca.log(ca.fmax(z, eps)), math.log(eps) + (z - eps) / eps)


def _guarded(node: Node, args: list):
    """(guarded expression, what was guarded) for sqrt, log, log10 and z^p with a constant
    0 < p < 1, whose derivative is infinite at 0 and whose value is NaN below; else (None, None).

    Why: the derivative of sqrt(max(h, 0)) at h = 0 is infinite, and the first Jacobian of a fit
    whose unmeasured level starts at 0 ended the fit with Invalid_Number_Detected.
    """
    if node[0] == "call" and node[1] == "sqrt":
        return _root_guard(args[0], 0.5), "sqrt"
    if node[0] == "call" and node[1] in ("log", "log10"):
        guarded = _log_guard(args[0])
        return (guarded if node[1] == "log" else guarded / math.log(10.0)), node[1]
    if node[0] == "bin" and node[1] == "^" and _is_number(args[1]) and 0.0 < args[1] < 1.0:
        return _root_guard(args[0], float(args[1])), "power"
    return None, None


def to_casadi(node: Node, env: Mapping[str, object], where: str, guards: list[str] | None = None):
    """Build the CasADi expression of `node` with names looked up in `env`.

    Sub-expressions of numbers only are folded to numbers (and refused if not finite and real).
    With a list `guards`, roots and logarithms of non-constant arguments are guarded near 0
    (`_guarded`) and each is recorded there as "<where>: <sub-expression>".

    Parameters
    ----------
    node : Node
        An AST from `parse`.
    env : Mapping
        Names -> CasADi expressions or numbers; ``pi`` and ``e`` are known besides.
    where : str
        Field path named in the errors.
    guards : list of str or None, optional
        Collects the guarded sub-expressions (appended to in place); None: no guard.

    Returns
    -------
    casadi.SX or casadi.MX or float
        The expression, or a number when `node` involves numbers only.

    Raises
    ------
    ModelDefinitionError
        On a name neither in `env` nor a constant, or a constant sub-expression that is not finite
        and real.
    """
    def combine(current: Node, args: list):
        kind = current[0]
        if kind == "num":
            return current[1]
        if kind == "name":
            name = current[1]
            if name in env:
                return env[name]
            if name in CONSTANTS:
                return CONSTANTS[name]
            raise ModelDefinitionError(f"unknown name '{name}' at column {current[2]}", where)
        if all(_is_number(a) for a in args):
            return _fold(current, args, where)
        if guards is not None:
            guarded, _ = _guarded(current, args)
            if guarded is not None:
                guards.append(f"{where}: {unparse(current)}")
                return guarded
        return _apply(current, args)

    return _postorder(node, combine)


def compile_expression(text: str, env: Mapping[str, object], where: str, guards: list[str] | None = None):
    """Parse and compile in one go.

    Parameters
    ----------
    text : str
        The expression.
    env, where, guards
        As in `to_casadi`.

    Returns
    -------
    casadi.SX or casadi.MX or float
        As `to_casadi`.

    Raises
    ------
    ModelDefinitionError
        As `parse` and `to_casadi`.
    """
    return to_casadi(parse(text, where), env, where, guards)


_PRECEDENCE = {"cmp": 1, "+": 2, "-": 2, "*": 3, "/": 3, "neg": 4, "^": 5}


def _precedence(node: Node) -> int:
    kind = node[0]
    if kind in ("bin", "cmp"):
        return _PRECEDENCE["cmp" if kind == "cmp" else node[1]]
    return _PRECEDENCE["neg"] if kind == "neg" else 99


def _number_text(value: float) -> str:
    return repr(value) if value != int(value) or abs(value) >= 1e15 else str(int(value))


def unparse(node: Node) -> str:
    """AST back to grammar text (parenthesised where precedence needs it).

    Parameters
    ----------
    node : Node
        An AST from `parse`.

    Returns
    -------
    str
        The expression in the grammar of this module; it parses back to the same expression.
    """
    def wrap(child: Node, text: str, prec: int) -> str:
        return f"({text})" if _precedence(child) < prec else text

    def combine(current: Node, texts: list[str]) -> str:
        kind = current[0]
        if kind == "num":
            return _number_text(current[1])
        if kind == "name":
            return current[1]
        kids = _children(current)
        if kind == "neg":
            return f"-{wrap(kids[0], texts[0], _PRECEDENCE['neg'])}"
        if kind == "call":
            return f"{current[1]}({', '.join(texts)})"
        op = current[1]
        prec = _precedence(current)
        if op == "^":   # right associative
            return f"{wrap(kids[0], texts[0], prec + 1)}^{wrap(kids[1], texts[1], prec)}"
        right_prec = prec + 1 if op in ("-", "/") or kind == "cmp" else prec
        return f"{wrap(kids[0], texts[0], prec)} {op} {wrap(kids[1], texts[1], right_prec)}"

    return _postorder(node, combine)


def substitute(node: Node, name: str, replacement: Node) -> Node:
    """Replace every occurrence of the name `name` by the AST `replacement`.

    Parameters
    ----------
    node : Node
        The AST to rewrite (not changed in place).
    name : str
        The name to replace.
    replacement : Node
        The AST put in its place.

    Returns
    -------
    Node
        The rewritten AST.
    """
    def combine(current: Node, kids: list) -> Node:
        kind = current[0]
        if kind == "name":
            return replacement if current[1] == name else current
        if kind == "num":
            return current
        if kind == "neg":
            return ("neg", kids[0])
        if kind in ("bin", "cmp"):
            return (kind, current[1], kids[0], kids[1])
        return ("call", current[1], tuple(kids), current[3])

    return _postorder(node, combine)
