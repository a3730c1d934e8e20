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

import math
import re
from dataclasses import dataclass
from typing import Callable, Mapping, Union

import casadi as ca

from solvers.errors import ModelDefinitionError

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
            return ("num", float(tok.text))
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
        return ("call", fname, args, name.column)


def parse(text: str, where: str) -> Node:
    """Parse `text` into an AST; errors name `where` and the column."""
    return _Parser(text, where).parse()


def names_in(node: Node) -> set[str]:
    kind = node[0]
    if kind == "name":
        return {node[1]}
    if kind == "num":
        return set()
    if kind == "neg":
        return names_in(node[1])
    if kind in ("bin", "cmp"):
        return names_in(node[2]) | names_in(node[3])
    return set().union(*(names_in(a) for a in node[2]))


def to_casadi(node: Node, env: Mapping[str, object], where: str):
    """Build the CasADi expression of `node` with names looked up in `env`."""
    kind = node[0]
    if kind == "num":
        return node[1]
    if kind == "name":
        name = node[1]
        if name in env:
            return env[name]
        if name in CONSTANTS:
            return CONSTANTS[name]
        raise ModelDefinitionError(f"unknown name '{name}' at column {node[2]}", where)
    if kind == "neg":
        return -to_casadi(node[1], env, where)
    if kind == "bin":
        a, b = to_casadi(node[2], env, where), to_casadi(node[3], env, where)
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
        a, b = to_casadi(node[2], env, where), to_casadi(node[3], env, where)
        return {"<": a < b, "<=": a <= b, ">": a > b, ">=": a >= b,
                "==": a == b, "!=": a != b}[node[1]]
    fname, args = node[1], [to_casadi(a, env, where) for a in node[2]]
    if fname in _UNARY:
        return _UNARY[fname](args[0])
    if fname in _BINARY:
        return _BINARY[fname](args[0], args[1])
    return ca.if_else(args[0], args[1], args[2])


def compile_expression(text: str, env: Mapping[str, object], where: str):
    """Parse and compile in one go."""
    return to_casadi(parse(text, where), env, where)


_PRECEDENCE = {"cmp": 1, "+": 2, "-": 2, "*": 3, "/": 3, "neg": 4, "^": 5}


def unparse(node: Node) -> str:
    """AST back to grammar text (parenthesised where precedence needs it)."""
    kind = node[0]
    if kind == "num":
        return repr(node[1]) if node[1] != int(node[1]) or abs(node[1]) >= 1e15 else str(int(node[1]))
    if kind == "name":
        return node[1]
    if kind == "neg":
        return f"-{_wrap(node[1], _PRECEDENCE['neg'])}"
    if kind == "call":
        return f"{node[1]}({', '.join(unparse(a) for a in node[2])})"
    op = node[1]
    prec = _PRECEDENCE["cmp" if kind == "cmp" else op]
    if op == "^":   # right associative
        return f"{_wrap(node[2], prec + 1)}^{_wrap(node[3], prec)}"
    right_prec = prec + 1 if op in ("-", "/") or kind == "cmp" else prec
    return f"{_wrap(node[2], prec)} {op} {_wrap(node[3], right_prec)}"


def _wrap(node: Node, prec: int) -> str:
    kind = node[0]
    mine = _PRECEDENCE["cmp" if kind == "cmp" else node[1]] if kind in ("bin", "cmp") else \
        _PRECEDENCE["neg"] if kind == "neg" else 99
    text = unparse(node)
    return f"({text})" if mine < prec else text


def substitute(node: Node, name: str, replacement: Node) -> Node:
    """Replace every occurrence of the name `name` by the AST `replacement`."""
    kind = node[0]
    if kind == "name":
        return replacement if node[1] == name else node
    if kind == "num":
        return node
    if kind == "neg":
        return ("neg", substitute(node[1], name, replacement))
    if kind in ("bin", "cmp"):
        return (kind, node[1], substitute(node[2], name, replacement), substitute(node[3], name, replacement))
    return ("call", node[1], [substitute(a, name, replacement) for a in node[2]], node[3])
