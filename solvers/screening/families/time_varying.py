"""A declared parameter that changes in time: switch times (steps) or a linear drift.

Both are true of the record they are found in, not of new data (`record_specific`): on a validation
record with its own clock the estimation record's times mean nothing, so validation sees them
switched off; on one that continues the estimation record in time they are laws of t and go on
(`confirm.off_on_validation`).
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from greyfit.schemas.model import Model
from greyfit.solvers.screening.augment import fresh_name, replace_parameter, with_parameter
from greyfit.solvers.screening.candidate import Candidate, LibraryContext, fmt
from greyfit.solvers.screening.families.base import NeedsTracedEquation, Scope, bind, param_regressor, shared_free

MAX_SWITCHES = 6   # switch times of one parameter chosen jointly at most
# candidate switch times per parameter: every column is propagated through the output sensitivities
# and searched by forward selection, so the grid sets the cost of the step screen; 200 places a switch
# within 0.5 % of the record (seed 000's k4 within 5 ms of 1 s) at a third of the cost of 600
STEP_GRID = 200


def varying_parameters(ctx: LibraryContext) -> list[tuple[str, int]]:
    """(name, index) of the shared free parameters some traced equation depends on.

    Parameters
    ----------
    ctx : LibraryContext
        The model and the fitted trajectory.

    Returns
    -------
    list of tuple of (str, int)
        Parameter name and its index in the compiled parameter vector.
    """
    cm = ctx.trace.cm
    ones = [np.ones_like(t) for t in ctx.trace.t]
    out = []
    for name in shared_free(ctx.model):
        j = cm.parameters.index(name)
        if param_regressor(ctx.trace, j, ones):
            out.append((name, j))
    return out


class ParameterStep:
    """Switch times of a piecewise-constant parameter by forward selection over a time grid.

    One step rarely explains a parameter that switches back and forth (the spring k4 of the LMI-based
    identification of physical parameters alternates at 0.25/0.5/0.75 s), so the switch times are
    chosen jointly, each kept while its partial F-test passes at `significance` divided by the grid size.
    """

    name = "parameter_step"
    scope: Scope = "parameter"
    generic = False

    def supports(self, ctx: LibraryContext) -> bool:
        """Whether the loop gives a scorer to select switch times with.

        Parameters
        ----------
        ctx : LibraryContext
            The model, the fitted trajectory and the discovery options.

        Returns
        -------
        bool
            True when the loop gives a scorer to select switch times with.
        """
        return ctx.scorer_for is not None

    def rewrite(self, model: Model, **spec: Any) -> tuple[Model, list[str]]:
        """`model` with p replaced by p + Σ d_i·[t ≥ τ_i], one new parameter per switch time.

        Parameters
        ----------
        model : Model
            The model to rewrite (not changed: a copy is returned).
        **spec : Any
            `parameter`: p; `taus`: the switch times τ_i, s.

        Returns
        -------
        tuple of (Model, list of str)
            The rewritten model and the new parameters' names.

        Raises
        ------
        ModelDefinitionError
            When a rewritten expression does not parse.
        """
        name, taus = spec["parameter"], spec["taus"]
        names, terms = [], []
        for tau in taus:
            d = fresh_name(model, f"d{name}_step")
            model = with_parameter(model, d, 0.0)
            names.append(d)
            terms.append(f"{d}*if_else(t >= {fmt(tau)}, 1, 0)")
        return replace_parameter(model, name, f"({name} + {' + '.join(terms)})"), names

    def candidates(self, ctx: LibraryContext) -> list[Candidate]:
        """Switch times of every varying parameter, chosen jointly by forward selection on a time grid.

        Parameters
        ----------
        ctx : LibraryContext
            The model, the fitted trajectory and the discovery options.

        Returns
        -------
        list of Candidate
            At most one candidate per parameter (record-specific), its switch times within the 3-97 %
            quantiles of the record's time.
        """
        t_all = np.concatenate(ctx.trace.t)
        t_lo, t_hi = np.quantile(t_all, 0.03), np.quantile(t_all, 0.97)
        out = [self._one(ctx, name, j, t_lo, t_hi) for name, j in varying_parameters(ctx)]
        return [c for c in out if c is not None]

    def _one(self, ctx: LibraryContext, name: str, j: int, t_lo: float, t_hi: float) -> Candidate | None:
        trace = ctx.trace
        t_all = np.concatenate(trace.t)
        grid = np.unique(t_all[(t_all >= t_lo) & (t_all <= t_hi)])
        if grid.size > STEP_GRID:
            grid = grid[np.linspace(0, grid.size - 1, STEP_GRID).astype(int)]
        base = param_regressor(trace, j, [np.ones_like(t) for t in trace.t])
        if not base or ctx.scorer_for is None:
            return None
        chosen = _select_switches(ctx, base, grid, t_all)
        if not chosen:
            return None
        taus = sorted(float(grid[c]) for c in chosen)
        final = {i: [np.column_stack([c * (t >= tau) for tau in taus]) for c, t in zip(cols, trace.t)]
                 for i, cols in base.items()}
        when = ", ".join(fmt(tau) for tau in taus)
        # the switch times are a subset chosen jointly from the grid: its share of the level (grid·m of the
        # Bonferroni count) is split among the C(grid, m) subsets of its size, and among the sizes the
        # selection may end at. Counting grid·m alone let forward selection over-fit coloured noise.
        tries = int(grid.size) * len(taus)
        multiplicity = max(MAX_SWITCHES * math.comb(int(grid.size), len(taus)) / tries, 1.0)
        return Candidate(self.name, final, f"{name} -> {name} + steps at t = {when}",
                         f"{name} changes value at t = {when} s", bind(self, parameter=name, taus=taus),
                         family=f"parameter_step:{name}", tries=tries, record_specific=True,
                         multiplicity=multiplicity, modifies=name, variables=("t",),
                         searched=len(taus))


def _select_switches(ctx: LibraryContext, base, grid: np.ndarray, t_all: np.ndarray) -> list[int]:
    """Forward selection by gain alone (a single switch of a parameter that switches back and forth
    explains little, so no per-step test), then drop switches that add too little jointly; the joint
    significance test and the confirming refit judge the result."""
    trace = ctx.trace
    if ctx.scorer_for is None:
        return []
    scorer = ctx.scorer_for(sorted(base))
    steps = {i: [c[:, None] * (t[:, None] >= grid[None, :]) for c, t in zip(cols, trace.t)]
             for i, cols in base.items()}
    columns = scorer.stack(steps)
    min_gain = ctx.min_explained / 2.5
    chosen = scorer.forward_select(columns, max_columns=MAX_SWITCHES, alpha=1.0, min_gain=min_gain)
    chosen = scorer.prune(columns, chosen, min_gain)
    # a value held for a few samples is a patch for a slightly misplaced switch, not a parameter change
    dwell = max(5 * float(np.median(np.diff(grid))), 0.01 * float(t_all.max() - t_all.min()))
    kept: list[int] = []
    for c in chosen:   # in order of selection: the stronger switch of a close pair stays
        if all(abs(grid[c] - grid[k]) >= dwell for k in kept):
            kept.append(c)
    return scorer.prune(columns, kept, min_gain)


class ParameterDrift(NeedsTracedEquation):
    """θ -> θ + dθ/dt·(t − t̄): a slow change over the record (a clogging outlet, a warming motor)."""

    name = "parameter_drift"
    scope: Scope = "parameter"
    generic = False

    def rewrite(self, model: Model, **spec: Any) -> tuple[Model, list[str]]:
        """`model` with p replaced by p + d·(t − t̄), d a new parameter.

        Parameters
        ----------
        model : Model
            The model to rewrite (not changed: a copy is returned).
        **spec : Any
            `parameter`: p; `t_mid`: t̄, the mean time of the record, s.

        Returns
        -------
        tuple of (Model, list of str)
            The rewritten model and the new parameter's name.

        Raises
        ------
        ModelDefinitionError
            When a rewritten expression does not parse.
        """
        name, t_mid = spec["parameter"], spec["t_mid"]
        d = fresh_name(model, f"d{name}_dt")
        model = with_parameter(model, d, 0.0)
        return replace_parameter(model, name, f"({name} + {d}*(t - {fmt(t_mid)}))"), [d]

    def candidates(self, ctx: LibraryContext) -> list[Candidate]:
        """A linear drift in time of every varying parameter.

        Parameters
        ----------
        ctx : LibraryContext
            The model, the fitted trajectory and the discovery options.

        Returns
        -------
        list of Candidate
            One candidate per parameter (record-specific).
        """
        t_mid = float(np.mean(np.concatenate(ctx.trace.t)))
        out = []
        for name, j in varying_parameters(ctx):
            reg = param_regressor(ctx.trace, j, [t - t_mid for t in ctx.trace.t])
            out.append(Candidate(self.name, reg, f"{name} -> {name} + d{name}_dt*(t - {fmt(t_mid)})",
                                 f"{name} drifts linearly in time", bind(self, parameter=name, t_mid=t_mid),
                                 family=f"parameter_drift:{name}", record_specific=True, modifies=name,
                                 variables=("t",)))
        return out
