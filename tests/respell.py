"""Random algebraically equivalent spellings of a model: the same equations written another way.

`respell(model, rng)` rewrites every state equation a few times at random nodes of its parse tree:
a difference's sides swapped with the sign (a − b → −(b − a)), sums and products reordered, products
distributed over sums and common factors taken out, a quotient split over its numerator, a division by
p written as a product with 1/p and back, a negation moved into a factor or written as −1·x, a square
written as x·x, and sub-expressions moved into new intermediate definitions. Numbers stay exact
(2·(x/2) and −1·x are exact in floating point), so the spelling changes and the values do not, to
rounding.
"""
from __future__ import annotations

import copy

import numpy as np

from greyfit.solvers.model.expressions import _children, parse, unparse

Node = tuple


def _swap_difference(n: Node) -> Node | None:
    return ("neg", ("bin", "-", n[3], n[2])) if n[0] == "bin" and n[1] == "-" else None


def _reorder(n: Node) -> Node | None:
    if n[0] == "bin" and n[1] in ("+", "*"):
        return ("bin", n[1], n[3], n[2])
    if n[0] == "bin" and n[1] == "-":
        return ("bin", "+", ("neg", n[3]), n[2])
    return None


def _distribute(n: Node) -> Node | None:
    if n[0] != "bin" or n[1] != "*":
        return None
    left, right = n[2], n[3]
    if right[0] == "bin" and right[1] in ("+", "-"):
        return ("bin", right[1], ("bin", "*", left, right[2]), ("bin", "*", left, right[3]))
    if left[0] == "bin" and left[1] in ("+", "-"):
        return ("bin", left[1], ("bin", "*", left[2], right), ("bin", "*", left[3], right))
    return None


def _factor(n: Node) -> Node | None:
    if n[0] == "bin" and n[1] in ("+", "-") and n[2][0] == n[3][0] == "bin" and n[2][1] == n[3][1] == "*" \
            and _same(n[2][2], n[3][2]):
        return ("bin", "*", n[2][2], ("bin", n[1], n[2][3], n[3][3]))
    return None


def _split_quotient(n: Node) -> Node | None:
    if n[0] == "bin" and n[1] == "/" and n[2][0] == "bin" and n[2][1] in ("+", "-"):
        return ("bin", n[2][1], ("bin", "/", n[2][2], n[3]), ("bin", "/", n[2][3], n[3]))
    return None


def _inverse(n: Node) -> Node | None:
    if n[0] == "bin" and n[1] == "/" and n[2] != ("num", 1.0):
        return ("bin", "*", n[2], ("bin", "/", ("num", 1.0), n[3]))
    if n[0] == "bin" and n[1] == "*" and n[3][0] == "bin" and n[3][1] == "/" and n[3][2] == ("num", 1.0):
        return ("bin", "/", n[2], n[3][3])
    return None


def _negation(n: Node) -> Node | None:
    if n[0] == "neg" and n[1][0] == "bin" and n[1][1] in ("*", "/"):
        return ("bin", n[1][1], ("neg", n[1][2]), n[1][3])
    if n[0] == "neg":
        return ("bin", "*", ("num", -1.0), n[1])
    return None


def _halve(n: Node) -> Node | None:
    if n[0] == "bin" and n[1] == "^" and n[3] == ("num", 2.0):
        return ("bin", "*", n[2], n[2])
    if n[0] in ("name", "bin", "call"):
        return ("bin", "*", ("num", 2.0), ("bin", "/", n, ("num", 2.0)))
    return None


RULES = (_swap_difference, _reorder, _distribute, _factor, _split_quotient, _inverse, _negation, _halve)


def _same(a: Node, b: Node) -> bool:
    return unparse(a) == unparse(b)


def _paths(node: Node, path: tuple = ()) -> list[tuple]:
    out = [path]
    for k, child in enumerate(_children(node)):
        out += _paths(child, path + (k,))
    return out


def _get(node: Node, path: tuple) -> Node:
    for k in path:
        node = _children(node)[k]
    return node


def _put(node: Node, path: tuple, new: Node) -> Node:
    if not path:
        return new
    kids = list(_children(node))
    kids[path[0]] = _put(kids[path[0]], path[1:], new)
    if node[0] == "neg":
        return ("neg", kids[0])
    if node[0] in ("bin", "cmp"):
        return (node[0], node[1], kids[0], kids[1])
    return ("call", node[1], tuple(kids), node[3])


def rewrite(node: Node, rng: np.random.Generator, times: int) -> Node:
    """`times` random rewrites at random nodes (a node no rule applies to is left as it is)."""
    for _ in range(times):
        path = _paths(node)[int(rng.integers(len(_paths(node))))]
        target = _get(node, path)
        for k in rng.permutation(len(RULES)):
            new = RULES[k](target)
            if new is not None:
                node = _put(node, path, new)
                break
    return node


def _define(node: Node, rng: np.random.Generator, definitions: dict[str, str], stem: str) -> Node:
    """Move a random compound sub-expression into a new definition (the equation then names it)."""
    compound = [p for p in _paths(node) if _get(node, p)[0] in ("bin", "call", "neg")]
    if not compound:
        return node
    path = compound[int(rng.integers(len(compound)))]
    name = f"{stem}_{len(definitions)}"
    definitions[name] = unparse(_get(node, path))
    return _put(node, path, ("name", name, 0))


def respell(model: dict, rng: np.random.Generator, max_rewrites: int = 8, define: float = 0.5) -> dict:
    """The model with every state equation respelt (its declarations and outputs kept).

    Parameters
    ----------
    model : dict
        A model in greyfit's JSON contract.
    rng : numpy.random.Generator
        The source of the rewrites.
    max_rewrites : int
        Up to this many rewrites per equation.
    define : float
        Chance that an equation hands a sub-expression to a new definition.

    Returns
    -------
    dict
        A copy with new `equations` text and maybe new `definitions` (appended after the model's own).
    """
    out = copy.deepcopy(model)
    definitions = dict(model.get("definitions") or {})
    for s, text in model["equations"].items():
        node = rewrite(parse(text, f"equations.{s}"), rng, int(rng.integers(1, max_rewrites + 1)))
        if rng.random() < define:
            node = _define(node, rng, definitions, f"r_{s}")
        out["equations"][s] = unparse(node)
    out["definitions"] = definitions
    return out


def request_of(model: dict, experiment: dict):
    """The fit request the respelling checks screen at (multiple shooting, inputs linear)."""
    from greyfit.schemas.fit import FitRequest
    return FitRequest.model_validate({"model": model, "experiments": [experiment], "method": "multiple_shooting"})


def screen_of(model: dict, experiment: dict, fit, options=None, output_scorer=None):
    """The discovery screen of `model` at the fit `fit` (a fit of any spelling of it: its parameters are
    by name); `output_scorer`, one built at this fit for another spelling, saves the sensitivities."""
    from greyfit.schemas.discovery import DiscoveryOptions
    from greyfit.solvers.screening.screening import screen
    return screen(request_of(model, experiment), fit, options or DiscoveryOptions(), set(), output_scorer)


def candidate_set(model: dict, experiment: dict, fit, options=None, output_scorer=None) -> tuple[set, list]:
    """((effect, equations, outputs, term, where scored) of every candidate screened, the same of the
    significant ones in the screen's ranking) of `model` at the fit `fit` (`screen_of`).

    Parameters
    ----------
    model : dict
        The model (any spelling).
    experiment : dict
        The record.
    fit : FitResult
        A fit of the model.
    options : DiscoveryOptions or None
        The screen's options (the defaults when None).
    output_scorer : OutputScorer or None
        The output sensitivities at this fit, when already built.

    Returns
    -------
    tuple of (set, list)
        All candidates, and the significant ones, best first.
    """
    s = screen_of(model, experiment, fit, options, output_scorer)

    def key(sc):
        c = sc.candidate
        return (c.effect, tuple(sorted(c.equations)), tuple(sorted(c.outputs or {})), c.term, sc.scored_on)
    return {key(sc) for sc in s.scored}, [key(sc) for sc in s.scored if sc.significant]
