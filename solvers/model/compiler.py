"""Compile a `schemas.Model` once into CasADi Functions f(x,u,p,t) and h(x,u,p,t)."""
from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from greyfit.schemas.fit import FitWarning
from greyfit.schemas.model import Model
from greyfit.solvers.errors import ModelDefinitionError
from greyfit.solvers.model.constraints import compile_constraints
from greyfit.solvers.model.expressions import GUARD_EPSILON, compile_expression, parse, to_casadi


@dataclass
class CompiledModel:
    """CasADi form of a model; `p` is the full physical parameter vector in declaration order."""

    model: Model
    states: list[str]
    inputs: list[str]
    parameters: list[str]
    outputs: list[str]
    output_expressions: dict[str, str]
    rhs: ca.Function   # (x, u, p, t) -> dx/dt
    output: ca.Function  # (x, u, p, t) -> y
    constraint: ca.Function | None  # (p) -> g, with g >= 0 (or g == 0 where marked)
    constraint_equality: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    direct_outputs: dict[str, str] = field(default_factory=dict)  # output name -> state it measures
    # "<field>: <sub-expression>" of each root or logarithm compiled with its guard near 0
    # (expressions.GUARD_EPSILON); reported by `guard_notes`
    guarded: list[str] = field(default_factory=list)
    # Functions derived from this model (integrator steps by their options, ∂f/∂x, ...), built once;
    # init=False: dataclasses.replace gives a changed model a fresh, empty cache
    derived: dict[tuple, object] = field(default_factory=dict, init=False, repr=False, compare=False)

    def derive(self, key: tuple, build):
        """What `build()` makes from this model (Functions, structure facts), built on first use.

        Parameters
        ----------
        key : tuple
            Names what is derived (e.g. ``("step", integrator, substeps, interpolation)``).
        build : callable
            No-argument callable making it; called only the first time `key` is asked for.

        Returns
        -------
        object
            The cached result of `build()`.
        """
        if key not in self.derived:
            self.derived[key] = build()
        return self.derived[key]

    @property
    def nx(self) -> int:
        """Number of states.

        Returns
        -------
        int
        """
        return len(self.states)

    @property
    def nu(self) -> int:
        """Number of inputs.

        Returns
        -------
        int
        """
        return len(self.inputs)

    @property
    def np(self) -> int:
        """Number of parameters (fixed and free) in the full physical parameter vector.

        Returns
        -------
        int
        """
        return len(self.parameters)

    @property
    def ny(self) -> int:
        """Number of outputs.

        Returns
        -------
        int
        """
        return len(self.outputs)

    def equation_parameters(self) -> dict[str, set[str]]:
        """Which parameters each state equation depends on, definitions expanded.

        Read from the sparsity of ∂f/∂p, computed once per model.

        Returns
        -------
        dict of str to set of str
            Per state name, the names of the parameters its equation depends on (a copy the caller may
            change).
        """
        deps = self.derive(("equation_parameters",), self._equation_parameters)
        return {s: set(v) for s, v in deps.items()}   # a copy: callers may change theirs

    def _equation_parameters(self) -> dict[str, set[str]]:
        x, u, p, t = _symbols(self)
        rows, cols = ca.jacobian(self.rhs(x, u, p, t), p).sparsity().get_triplet()
        deps: dict[str, set[str]] = {s: set() for s in self.states}
        for i, j in zip(rows, cols):
            deps[self.states[i]].add(self.parameters[j])
        return deps


def guard_notes(cm: CompiledModel) -> list[FitWarning]:
    """The info warning that roots and logarithms were guarded near 0 (none if there are none).

    Parameters
    ----------
    cm : CompiledModel
        The compiled model; `guarded` lists the guarded sub-expressions.

    Returns
    -------
    list of FitWarning
        One ``singular_derivative_guarded`` warning naming the expressions and the guard's epsilon,
        or an empty list.
    """
    if not cm.guarded:
        return []
    return [FitWarning(
        code="singular_derivative_guarded",
        message=f"{'; '.join(cm.guarded)}: exact for arguments ≥ {GUARD_EPSILON:g}; below, a C¹ "
                "polynomial (roots) or the tangent (logarithms) with a finite derivative, also for "
                "negative arguments, so a trajectory that touches 0 does not end the fit with NaN",
        detail={"expressions": list(cm.guarded), "epsilon": GUARD_EPSILON})]


def _symbols(cm: "CompiledModel"):
    return (ca.SX.sym("x", cm.nx), ca.SX.sym("u", cm.nu), ca.SX.sym("p", cm.np), ca.SX.sym("t"))


_COMPILED: "OrderedDict[str, CompiledModel]" = OrderedDict()
COMPILED_CACHE_SIZE = 64


def compile_model(model: Model) -> CompiledModel:
    """Build rhs/output/constraint Functions; raises ModelDefinitionError naming the field.

    A worker keeps the last models it compiled (keyed by their full JSON): a batch of fits of one
    model parses it once, and the Functions built from it (steps, compiled C) are found again.

    Parameters
    ----------
    model : Model
        The model as received.

    Returns
    -------
    CompiledModel
        The CasADi form: f(x, u, p, t), h(x, u, p, t), the constraint function g(p) and the names;
        the cached one when the same model was compiled before.

    Raises
    ------
    ModelDefinitionError
        When an equation, output, definition or constraint does not parse or uses an unknown name,
        or the model has no output; `field` names it.
    """
    key = model.model_dump_json()
    if key in _COMPILED:
        _COMPILED.move_to_end(key)
        return _COMPILED[key]
    cm = _compile(model)
    _COMPILED[key] = cm
    while len(_COMPILED) > COMPILED_CACHE_SIZE:
        _COMPILED.popitem(last=False)
    return cm


# the largest model graph (CasADi instructions, shared sub-expressions counted once) and its Jacobian
# with respect to states and parameters that a fit derives: every method differentiates the model, a
# fit evaluates it per sample and RK4 substep, and the compiled kernels grow with it. A physical model
# of the sizes the schema allows stays far below (the 4-DOF seat: ~100; 50 states of a linear
# template: ~5 000); a runaway one (a long chain of definitions, an expression repeated thousands of
# times) is refused here, in milliseconds, before anything is derived or compiled to C.
MAX_MODEL_INSTRUCTIONS = 20_000
MAX_JACOBIAN_INSTRUCTIONS = 200_000


def check_graph_size(model: Model, rhs: ca.Function, out: ca.Function, dx: ca.SX, symbols: list) -> None:
    """Refuse a model whose graph or first derivative is larger than a fit can afford.

    Parameters
    ----------
    model : Model
        The model (its equations name the field in the error).
    rhs, out : casadi.Function
        f(x, u, p, t) and h(x, u, p, t) in SX.
    dx : casadi.SX
        f's expression.
    symbols : list of casadi.SX
        x, u, p, t.

    Raises
    ------
    ModelDefinitionError
        Naming the largest equation (or output) and the limit.
    """
    size = rhs.n_instructions() + out.n_instructions()
    x, _, p, _ = symbols
    if size <= MAX_MODEL_INSTRUCTIONS:
        derivative = ca.Function("derivative", symbols, [ca.jacobian(dx, ca.vertcat(x, p))]).n_instructions()
        if derivative <= MAX_JACOBIAN_INSTRUCTIONS:
            return
        what = f"its derivative has {derivative} operations, the limit is {MAX_JACOBIAN_INSTRUCTIONS}"
    else:
        what = f"{size} operations after its definitions are inlined, the limit is {MAX_MODEL_INSTRUCTIONS}"
    sizes = {f"equations.{s}": ca.Function("equation", symbols, [dx[i]]).n_instructions()
             for i, s in enumerate(model.states)}
    field = max(sizes, key=lambda k: sizes[k])
    raise ModelDefinitionError(f"the model is too large to fit: {what}; the largest is {field} "
                               f"({sizes[field]} operations): simplify it or share sub-expressions "
                               "through definitions", field)


def _compile(model: Model) -> CompiledModel:
    x = ca.SX.sym("x", len(model.states))
    u = ca.SX.sym("u", len(model.inputs))
    params = [p.name for p in model.parameters]
    p = ca.SX.sym("p", len(params))
    t = ca.SX.sym("t")
    env: dict[str, object] = {"t": t}
    env.update({n: x[i] for i, n in enumerate(model.states)})
    env.update({n: u[i] for i, n in enumerate(model.inputs)})
    env.update({n: p[i] for i, n in enumerate(params)})
    env.update(model.constants)
    guarded: list[str] = []
    for name, text in model.definitions.items():
        env[name] = compile_expression(text, env, f"definitions.{name}", guarded)

    dx = ca.vertcat(*[compile_expression(model.equations[s], env, f"equations.{s}", guarded)
                      for s in model.states])
    outputs = model.measured_outputs()
    if not outputs:
        raise ModelDefinitionError("at least one output is needed", "outputs")
    direct = {}
    y_list = []
    for name, text in outputs.items():
        node = parse(text, f"outputs.{name}")
        if node[0] == "name" and node[1] in model.states:
            direct[name] = node[1]
        y_list.append(to_casadi(node, env, f"outputs.{name}", guarded))
    y = ca.vertcat(*y_list)

    constraint = None
    equality = np.zeros(0, dtype=bool)
    if model.constraints:
        param_names = {k for k in env if k not in model.states and k not in model.inputs}
        g, equality = compile_constraints(model.constraints, env, param_names, "constraints",
                                          forbidden=ca.vertcat(x, u, t))
        constraint = ca.Function("g", [p], [ca.vertcat(*g)])

    rhs = ca.Function("rhs", [x, u, p, t], [dx], ["x", "u", "p", "t"], ["dx"])
    out = ca.Function("output", [x, u, p, t], [y], ["x", "u", "p", "t"], ["y"])
    check_graph_size(model, rhs, out, dx, [x, u, p, t])
    for fn in (rhs, out):
        if fn.has_free():
            raise ModelDefinitionError(f"free symbols {fn.get_free()} in the model", "equations")
    return CompiledModel(
        model=model, states=list(model.states), inputs=list(model.inputs), parameters=params,
        outputs=list(outputs), output_expressions=outputs, rhs=rhs, output=out,
        constraint=constraint, constraint_equality=equality,
        direct_outputs=direct, guarded=guarded)
