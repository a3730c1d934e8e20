"""Parameter constraints ('a1*a2 - a3 >= 0', '<=', '==') compiled to g(p) >= 0 (== 0 where marked).

One compiler for every model kind (ODE models in `model_compiler`, transfer functions in
`frequency.polynomials`), so the grammar and the messages are the same everywhere.
"""
from __future__ import annotations

from collections.abc import Mapping

import casadi as ca
import numpy as np

from greyfit.solvers.errors import ModelDefinitionError
from greyfit.solvers.model.expressions import names_in, parse, to_casadi


def compile_constraints(texts: list[str], env: Mapping[str, object], allowed: set[str], field: str,
                        forbidden: ca.SX | None = None) -> tuple[list[ca.SX], np.ndarray]:
    """Each comparison as g with g >= 0 (g == 0 for '=='), and which of them are equalities.

    Parameters
    ----------
    texts : list of str
        The constraint texts; errors name ``{field}[i]``.
    env : Mapping
        Names -> CasADi expressions or numbers, as for `to_casadi`.
    allowed : set of str
        The names a constraint may use (parameters, constants, parameter-only definitions).
    field : str
        Field path of the constraint list, e.g. ``model.constraints``.
    forbidden : casadi.SX or None, optional
        Symbols a constraint must not depend on once definitions are expanded (x, u, t).

    Returns
    -------
    g : list of casadi.SX
        One expression per constraint, ≥ 0 (or = 0) where it holds: lhs − rhs for ``>``, ``>=``,
        ``==``, rhs − lhs for ``<``, ``<=``.
    equality : numpy.ndarray
        Boolean per constraint, True for ``==``.

    Raises
    ------
    ModelDefinitionError
        When a text does not parse, is not a comparison (or is ``!=``), uses a name outside
        `allowed`, or depends on `forbidden` symbols; names ``{field}[i]``.
    """
    g, equality = [], []
    for i, text in enumerate(texts):
        where = f"{field}[{i}]"
        node = parse(text, where)
        if node[0] != "cmp" or node[1] == "!=":
            raise ModelDefinitionError(
                "a constraint is a comparison such as 'a1*a2 - a3 >= 0' (<=, >=, == allowed)", where)
        used = names_in(node) - allowed - {"pi", "e"}
        if used:
            raise ModelDefinitionError(
                f"constraints may use parameters, constants and parameter-only definitions; "
                f"'{sorted(used)[0]}' is not one", where)
        lhs, rhs = to_casadi(node[2], env, where), to_casadi(node[3], env, where)
        expr = lhs - rhs if node[1] in (">", ">=", "==") else rhs - lhs
        if forbidden is not None and ca.depends_on(ca.SX(expr), forbidden):
            raise ModelDefinitionError("constraints may only involve parameters", where)
        g.append(expr)
        equality.append(node[1] == "==")
    return g, np.array(equality, dtype=bool)
