"""The user's own candidates (`discovery.candidates`): `parameter * (term)` added to an equation."""
from __future__ import annotations

from typing import Any

import casadi as ca
import numpy as np

from greyfit.schemas.model import Model
from greyfit.solvers.discovery.augment import add_term, fresh_name, with_parameter
from greyfit.solvers.discovery.candidate import Candidate, LibraryContext
from greyfit.solvers.discovery.families.base import Scope, bind
from greyfit.solvers.discovery.scoring_equations import TraceData
from greyfit.solvers.model.expressions import compile_expression, names_in, parse


class Custom:
    """Always screened when the request gives candidates (not an entry of `effects`)."""

    name = "custom"
    scope: Scope = "equation"
    generic = False

    def supports(self, ctx: LibraryContext) -> bool:
        return bool(ctx.custom)

    def rewrite(self, model: Model, **spec: Any) -> tuple[Model, list[str]]:
        cand = spec["cand"]
        name = fresh_name(model, cand.parameter)
        model = with_parameter(model, name, cand.value, cand.lower, cand.upper)
        return add_term(model, cand.equation, f"{name}*({cand.term})", "+"), [name]

    def candidates(self, ctx: LibraryContext) -> list[Candidate]:
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
    """Samples of every name a term may use (t, states, inputs, parameters, constants), per experiment."""
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
    """The expression `text` at every sample of every experiment."""
    names = list(env)
    syms = [ca.SX.sym(n) for n in names]
    expr = compile_expression(text, dict(zip(names, syms)), where)
    fn = ca.Function("term", syms, [expr])
    out = []
    for e in range(n_exp):
        n = env["t"][e].size
        out.append(np.array(fn.map(n)(*[np.asarray(env[k][e])[None, :] for k in names])).ravel())
    return out
