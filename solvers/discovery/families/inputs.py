"""What happens to an input before it acts: it saturates, or it acts whole samples late."""
from __future__ import annotations

from typing import Any

import numpy as np

from greyfit.schemas.model import Model
from greyfit.solvers.discovery.augment import fresh_name, replace_parameter, with_parameter
from greyfit.solvers.discovery.candidate import Candidate, LibraryContext, fmt
from greyfit.solvers.discovery.families.base import Scope, bind, sensitivity_regressor

MAX_LAG = 20   # samples


def _input_regressor(ctx: LibraryContext, k: int, change: list[np.ndarray]):
    return sensitivity_regressor(ctx.trace, ctx.trace.ju, k, change)


class Saturation:
    name = "saturation"
    scope: Scope = "input"
    generic = False

    def supports(self, ctx: LibraryContext) -> bool:
        return bool(ctx.trace.cm.inputs)

    def rewrite(self, model: Model, **spec: Any) -> tuple[Model, list[str]]:
        u, level = spec["input"], spec["level"]
        name = fresh_name(model, f"{u}_max")
        model = with_parameter(model, name, float(level), lower=0.0)
        return replace_parameter(model, u, f"min(max({u}, -{name}), {name})"), [name]

    def candidates(self, ctx: LibraryContext) -> list[Candidate]:
        out: list[Candidate] = []
        for k, u in enumerate(ctx.trace.cm.inputs):
            vals = ctx.input_values(u)
            mags = np.abs(np.concatenate(vals))
            if mags.max() <= 0:
                continue
            for level in np.unique(np.quantile(mags, np.linspace(0.5, 0.98, 13))):
                if level <= 0:
                    continue
                reg = _input_regressor(ctx, k, [np.clip(x, -level, level) - x for x in vals])
                if reg:
                    out.append(Candidate(self.name, reg, f"{u} -> min(max({u}, -{u}_max), {u}_max)",
                                         f"input {u} saturates near ±{fmt(level)}",
                                         bind(self, input=u, level=float(level)), sign=1.0,
                                         family=f"saturation:{u}", variables=(u,)))
        return out


class InputDelay:
    """The delay is a whole number of samples: the model language has no delay operator, so the
    delayed input enters as data (returned in `added_inputs`)."""

    name = "input_delay"
    scope: Scope = "input"
    generic = True

    def supports(self, ctx: LibraryContext) -> bool:
        return bool(ctx.trace.cm.inputs)

    def rewrite(self, model: Model, **spec: Any) -> tuple[Model, list[str]]:
        u, delayed = spec["input"], spec["delayed"]
        model = model.model_copy(update={"inputs": [*model.inputs, delayed]})
        return replace_parameter(model, u, delayed), []

    def candidates(self, ctx: LibraryContext) -> list[Candidate]:
        out: list[Candidate] = []
        dt = float(np.median(np.diff(ctx.trace.t[0])))
        for k, u in enumerate(ctx.trace.cm.inputs):
            delayed = fresh_name(ctx.model, f"{u}_delayed")
            for lag in range(1, MAX_LAG + 1):
                change = [np.concatenate([np.full(lag, x[0]), x[:-lag]]) - x for x in ctx.input_values(u)]
                reg = _input_regressor(ctx, k, change)
                if not reg:
                    continue
                out.append(Candidate(self.name, reg, f"{u}(t) -> {delayed} = {u}(t - {fmt(lag * dt)})",
                                     f"input {u} acts {lag} sample(s) ({fmt(lag * dt)} s) late",
                                     bind(self, input=u, delayed=delayed), sign=1.0, family=f"input_delay:{u}",
                                     refit_variants=True, generic=True, variables=(u,),
                                     transform_experiments=_delayed_data(u, delayed, lag)))
        return out


def _delayed_data(u: str, delayed: str, lag: int):
    def transform(experiments):
        out_exps = []
        for exp in experiments:
            series = list(exp.inputs[u])
            shifted = [series[0]] * lag + series[:-lag]
            out_exps.append(exp.model_copy(update={"inputs": {**exp.inputs, delayed: shifted}}))
        return out_exps
    return transform
