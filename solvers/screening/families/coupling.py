"""A nonlinear coupling between two bodies: the coefficient of a difference a − b grows with it.

A spring ks·(zs − zu) between two masses, a damper c·(vs − vu), a conductance U·A·(T − Ta): where the
coefficient's parameter p acts only on that difference (`canonical.CanonicalForm.linear_in`), p becomes
p + d·g(a − b) in every equation at once, so the law stays one force acting on both bodies with
opposite signs and their own masses:

- g = (a − b)²: the force gains a cubic part (a progressive or softening spring, d·(a − b)³);
- g = |a − b|: the force gains a quadratic part (turbulent or quadratic damping, d·(a − b)|a − b|).
"""
from __future__ import annotations

from typing import Any

import numpy as np

from greyfit.schemas.model import Model
from greyfit.solvers.screening.augment import fresh_name, replace_parameter, with_parameter
from greyfit.solvers.screening.candidate import Candidate, LibraryContext
from greyfit.solvers.screening.canonical import canonical_form
from greyfit.solvers.screening.families.base import NeedsTracedEquation, Scope, bind, param_regressor
from greyfit.solvers.screening.families.time_varying import varying_parameters

# (label, law in model syntax of the difference d, samples, what the coupling then is)
LAWS = (("2", "({d})^2", lambda d: d * d, "a cubic part: force ∝ ({d}) + β·({d})³"),
        ("abs", "abs({d})", np.abs, "a quadratic part: force ∝ ({d}) + β·({d})·|{d}|"))


class CouplingLaw(NeedsTracedEquation):
    name = "coupling_law"
    scope: Scope = "parameter"
    generic = False

    def rewrite(self, model: Model, **spec: Any) -> tuple[Model, list[str]]:
        """`model` with the coupling's parameter p replaced by p + β·g(a − b), β a new parameter.

        Parameters
        ----------
        model : Model
            The model to rewrite (not changed: a copy is returned).
        **spec : Any
            `parameter`: p; `law`: g(a − b) in model syntax; `stem`: the new parameter's stem.

        Returns
        -------
        tuple of (Model, list of str)
            The rewritten model and the new parameter's name.

        Raises
        ------
        ModelDefinitionError
            When a rewritten expression does not parse.
        """
        name = spec["parameter"]
        beta = fresh_name(model, spec["stem"])
        model = with_parameter(model, beta, 0.0)
        return replace_parameter(model, name, f"({name} + {beta}*{spec['law']})"), [beta]

    def candidates(self, ctx: LibraryContext) -> list[Candidate]:
        """Both laws of every coupling whose coefficient is one free parameter acting on it alone.

        Parameters
        ----------
        ctx : LibraryContext
            The model, the fitted trajectory and the discovery options.

        Returns
        -------
        list of Candidate
            Per (a, b, p) and law, one candidate (its column ∂f/∂p · g(a − b) in every equation p is in).
        """
        form = canonical_form(ctx.model)
        varying = dict(varying_parameters(ctx))
        out: list[Candidate] = []
        seen: set[tuple[str, str, str]] = set()
        for c in form.couplings:
            for p in c.scales:
                if p not in varying or form.linear_in.get(p) != frozenset((c.a, c.b)) or (c.a, c.b, p) in seen:
                    continue
                seen.add((c.a, c.b, p))
                out += self._laws(ctx, c.a, c.b, p, varying[p])
        return out

    def _laws(self, ctx: LibraryContext, a: str, b: str, p: str, j: int) -> list[Candidate]:
        diff = [x - y for x, y in zip(ctx.values(a), ctx.values(b))]
        d = f"{a} - {b}"
        variables = tuple(v for v in (a, b) if v in ctx.states or v in ctx.trace.cm.inputs)
        out = []
        for label, law, fn, what in LAWS:
            reg = param_regressor(ctx.trace, j, [fn(x) for x in diff])
            if not reg:
                continue
            stem = f"{p}_{a}_{b}{label}"
            text = law.format(d=d)
            c = Candidate(
                self.name, reg, f"{p} -> {p} + {stem}*{text}",
                f"the coupling {p}·({d}) gains {what.format(d=d)}",
                bind(self, parameter=p, law=text, stem=stem), family=f"{self.name}:{a}:{b}:{p}:{label}",
                modifies=p, variables=variables)
            # a power of the difference added to a linear coupling is a member of the series that
            # approximates any smooth law of it (as the power laws are): it names no mechanism, and a
            # named law of the same variables (radiation's T⁴, drag) is refitted beside it
            c.approximating = True
            out.append(c)
        return out
