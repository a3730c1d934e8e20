"""A saturable rate: a consumption or outflow of a positive quantity that saturates as the quantity
grows, −Vm·x/(K + x) (Michaelis–Menten kinetics, Monod growth on a substrate, a pump or a carrier
that can only move so much).

A model whose rates are linear in a concentration, a population or a level can only approximate it:
its declared rate constant absorbs the law's slope at small x, and is off wherever x spans K. The law
is offered in the equation of every state that is a positive quantity on the fitted trajectory
(`base.keeps_positive`), at a few starting half-saturation constants K (fractions and multiples of the
state's median); the refit estimates K with Vm. A saturating curve is the shape of many concave laws
(an orifice's √x among them), so the family is an approximating one: the named laws of the same state
are refitted beside it, and where it wins over one it `approximates`.
"""
from __future__ import annotations

from typing import Any

import numpy as np

from greyfit.schemas.model import Model
from greyfit.solvers.screening.augment import add_term, fresh_name, with_parameter
from greyfit.solvers.screening.candidate import Candidate, LibraryContext, fmt
from greyfit.solvers.screening.families.base import TermFamily, bind, keeps_positive

SCALES = (0.1, 0.3, 1.0, 3.0)   # starting K as multiples of the state's median: the refit chooses, then fits K


class SaturableRate(TermFamily):
    name = "saturable_rate"

    def rewrite(self, model: Model, **spec: Any) -> tuple[Model, list[str]]:
        """`model` with −Vm·x/(K + |x|) in d(equation)/dt; Vm ≥ 0 and K > 0 new parameters.

        Only Vm is returned as new: it says whether the law is there (Vm = 0: it is not); K is its
        shape, like the width of a smoothed switch, and is not tested against 0.

        Parameters
        ----------
        model : Model
            The model to augment (not changed: a copy is returned).
        **spec : Any
            `equation`: the state whose equation gets the term; `state`: x; `half`: the start of K;
            `top`: the upper bound of K.

        Returns
        -------
        tuple of (Model, list of str)
            The augmented model and the name of Vm.

        Raises
        ------
        ModelDefinitionError
            When the equation does not parse.
        """
        eq, x, half, top = spec["equation"], spec["state"], spec["half"], spec["top"]
        vm = fresh_name(model, f"Vm_{eq}")
        model = with_parameter(model, vm, 1e-6, lower=0.0)
        k = fresh_name(model, f"K_{eq}")
        model = with_parameter(model, k, float(half), lower=1e-3 * float(half), upper=float(top))
        return add_term(model, eq, f"{vm}*{x}/({k} + abs({x}))", "-"), [vm]

    def candidates(self, ctx: LibraryContext) -> list[Candidate]:
        """−Vm·x/(K + x) in the equation of every traced state x that keeps positive, per starting K.

        Parameters
        ----------
        ctx : LibraryContext
            The model, the fitted trajectory and the discovery options.

        Returns
        -------
        list of Candidate
            Per positive state, one candidate per K in `SCALES` times its median, variants of one
            family the refit chooses among, each marked approximating.
        """
        out: list[Candidate] = []
        for x in ctx.force_equations():
            vals = ctx.state_values(x)
            if not keeps_positive(vals):
                continue
            allv = np.concatenate(vals)
            median = float(np.median(np.abs(allv)))
            top = 10.0 * float(np.max(np.abs(allv)))
            if median <= 0 or not np.isfinite(top):
                continue
            for f in SCALES:
                half = f * median
                term = f"{x}/(K_{x} + {x})"
                c = self.term(ctx, x, [v / (half + np.abs(v)) for v in vals], term, f"Vm_{x}", "-", 0.0,
                              f"a saturable rate of {x} (Michaelis–Menten): −Vm·{x}/(K + {x}), K from "
                              f"{fmt(half)}", -1.0, (x,), refit_variants=True)
                if c is not None:
                    # the shape of many concave laws (Michaelis–Menten, an orifice's √x, a Hill law):
                    # a series member, refitted beside the named laws of x and `approximates` over them
                    c.approximating = True
                    c.term = f"- Vm_{x}*{x}/(K_{x} + {x})"
                    c.key = f"{c.family}|{c.term}|{fmt(half)}"
                    c.apply = bind(self, equation=x, state=x, half=half, top=max(top, 10 * half))
                    out.append(c)
        return out
