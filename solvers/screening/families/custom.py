"""The user's own candidates (`discovery.candidates`): `parameter * (term)` added to an equation."""
from __future__ import annotations

from typing import Any

import casadi as ca
import numpy as np

from greyfit.schemas.model import Model
from greyfit.solvers.model.expressions import compile_expression, names_in, parse
from greyfit.solvers.screening.augment import add_term, fresh_name, with_parameter
from greyfit.solvers.screening.candidate import Candidate, LibraryContext
from greyfit.solvers.screening.families.base import Scope, bind
from greyfit.solvers.screening.scoring_equations import TraceData


class Custom:
    """Always screened when the request gives candidates (not an entry of `effects`)."""

    name = "custom"
    scope: Scope = "equation"
    generic = False

    def supports(self, ctx: LibraryContext) -> bool:
        """Whether the request gives candidates of its own.

        Parameters
        ----------
        ctx : LibraryContext
            The model, the fitted trajectory and the discovery options.

        Returns
        -------
        bool
            True when the request gives candidates of its own.
        """
        return bool(ctx.custom)

    def rewrite(self, model: Model, **spec: Any) -> tuple[Model, list[str]]:
        """`model` with the user's term `p*(term)` added to its equation, p a new parameter.

        Parameters
        ----------
        model : Model
            The model to rewrite (not changed: a copy is returned).
        **spec : Any
            `cand`: the `CustomCandidate` (equation, term, parameter name, start value and bounds).

        Returns
        -------
        tuple of (Model, list of str)
            The augmented model and the new parameter's name (the candidate's, made unique).

        Raises
        ------
        ModelDefinitionError
            When a rewritten expression does not parse.
        """
        cand = spec["cand"]
        name = fresh_name(model, cand.parameter)
        model = with_parameter(model, name, cand.value, cand.lower, cand.upper)
        return add_term(model, cand.equation, f"{name}*({cand.term})", "+"), [name]

    def candidates(self, ctx: LibraryContext) -> list[Candidate]:
        """Each user candidate whose equation is traced, evaluated along the trajectory.

        Parameters
        ----------
        ctx : LibraryContext
            The model, the fitted trajectory and the discovery options.

        Returns
        -------
        list of Candidate
            One candidate per user candidate on a traced equation, in the request's order.

        Raises
        ------
        ModelDefinitionError
            When a term does not compile (`discovery.candidates[i].term`).
        """
        out: list[Candidate] = []
        env = numeric_env(ctx.trace)
        for ci, cand in enumerate(ctx.custom):
            if not ctx.traced(cand.equation):
                continue
            where = f"discovery.candidates[{ci}].term"
            vals = [np.asarray(v, dtype=float) for v in evaluate(cand.term, env, len(ctx.trace.t), where)]
            used = tuple(sorted(names_in(parse(cand.term, where)) & (set(ctx.states) | set(ctx.trace.cm.inputs))))
            out.append(Candidate(self.name, {ctx.states.index(cand.equation): vals},
                                 f"+ {cand.parameter}*({cand.term})",
                                 f"user candidate {cand.parameter}*({cand.term}) in d{cand.equation}/dt",
                                 bind(self, cand=cand), family=f"custom:{cand.parameter}", variables=used))
        return out


def numeric_env(trace: TraceData) -> dict:
    """Samples of every name a term may use (t, states, inputs, parameters, constants), per experiment.

    Parameters
    ----------
    trace : TraceData
        The fitted trajectory (time, states, inputs and parameter values per experiment).

    Returns
    -------
    dict
        Name to a list of (n_e,) arrays, one per experiment; parameters and constants repeated over the samples.
    """
    cm = trace.cm
    env: dict = {"t": trace.t}
    for i, s in enumerate(cm.states):
        env[s] = [x[i] for x in trace.x]
    for i, u in enumerate(cm.inputs):
        env[u] = [uu[i] for uu in trace.u]
    for j, p in enumerate(cm.parameters):
        env[p] = [np.full(t.size, pv[j]) for t, pv in zip(trace.t, trace.p)]
    env.update({k: [np.full(t.size, v) for t in trace.t] for k, v in cm.model.constants.items()})
    return env


def evaluate(text: str, env: dict, n_exp: int, where: str) -> list[np.ndarray]:
    """The expression `text` at every sample of every experiment.

    Parameters
    ----------
    text : str
        The expression (model syntax).
    env : dict
        Name to per-experiment samples (`numeric_env`); must hold "t".
    n_exp : int
        Number of experiments.
    where : str
        The expression's field, for error messages.

    Returns
    -------
    list of numpy.ndarray
        One (n_e,) array of values per experiment.

    Raises
    ------
    ModelDefinitionError
        When the expression does not compile or uses an unknown name (the field is `where`).
    """
    names = list(env)
    syms = [ca.SX.sym(n) for n in names]
    expr = compile_expression(text, dict(zip(names, syms)), where)
    fn = ca.Function("term", syms, [expr])
    out = []
    for e in range(n_exp):
        n = env["t"][e].size
        out.append(np.array(fn.map(n)(*[np.asarray(env[k][e])[None, :] for k in names])).ravel())
    return out
