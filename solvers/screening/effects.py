"""The library of candidate terms: every selected family of the registry (`families`) asked in turn.

`library` is the one place the registry is read. Two families may propose the same column (the
power x²·v and the quadratic law c(x) = c + b·x² of the damping acting on v): the earlier family in
the registry keeps it, so one hypothesis is counted once.
"""
from __future__ import annotations

from typing import Callable, Sequence, cast

import numpy as np

from greyfit.schemas.discovery import CustomCandidate
from greyfit.schemas.model import Model
from greyfit.solvers.screening.candidate import Candidate, LibraryContext, OutputFit, fmt, structure
from greyfit.solvers.screening.families import FAMILIES, USER, Family
from greyfit.solvers.screening.families.sensor import measured_values, quantisation_step
from greyfit.solvers.screening.scoring_equations import TraceData

__all__ = ["Candidate", "OutputFit", "library", "structure", "fmt"]

SAME_COLUMN = 1 - 1e-9   # |correlation| above which two single columns are one hypothesis


def library(model: Model, trace: TraceData, effects: Sequence[str], custom: Sequence[CustomCandidate],
            epsilon: float | None, scorer_for: Callable | None = None, significance: float = 0.01,
            min_explained: float = 0.05, outputs: OutputFit | None = None) -> tuple[list[Candidate], list[str]]:
    """Candidates of every selected family on this trace, and notes on what was not tried.

    Parameters
    ----------
    model : Model
        The fitted model.
    trace : TraceData
        Its fitted trajectory (`scoring_equations.build_trace`).
    effects : sequence of str
        Names of the families to ask (`DiscoveryOptions.effects`); user candidates always.
    custom : sequence of CustomCandidate
        The user's candidates (`DiscoveryOptions.candidates`).
    epsilon : float or None
        Smoothing width of sign-like terms; None: each family's own widths.
    scorer_for : callable or None
        Equations -> the scorer they are scored in (the step search selects in it).
    significance : float
        The screen's significance level.
    min_explained : float
        Smallest share of the residual a term must explain.
    outputs : OutputFit or None
        The fitted outputs, when the output path is screened (sensor families need them).

    Returns
    -------
    tuple of (list of Candidate, list of str)
        The candidates, registry order, duplicates dropped (`drop_duplicates`); notes on what was not
        tried or is noise (a quantised output).

    Raises
    ------
    ModelDefinitionError
        When a user candidate's term does not compile.
    """
    ctx = LibraryContext(model, trace, list(effects), list(custom), epsilon, scorer_for, significance,
                         min_explained, outputs)
    out: list[Candidate] = []
    for family in FAMILIES:
        if family.name in ctx.effects and family.supports(ctx):
            out += _candidates_of(family, ctx)
    if USER.supports(ctx):
        out += USER.candidates(ctx)
    if outputs is not None:
        ctx.notes += quantisation_notes(outputs)
    return drop_duplicates(out), ctx.notes


# what a family's own arithmetic can raise on a model it did not foresee; a model error
# (ModelDefinitionError) is the user's and still raises
FAMILY_FAILURES = (KeyError, IndexError, ValueError, ZeroDivisionError, FloatingPointError)


def _candidates_of(family: Family, ctx: LibraryContext) -> list[Candidate]:
    """The family's candidates; a family that fails on this model is left out with a note, so one
    family's blind spot never ends the search (every spelling of every model discovers)."""
    try:
        return family.candidates(ctx)
    except FAMILY_FAILURES as exc:
        ctx.notes.append(f"{family.name} not tried: it failed on this model ({type(exc).__name__}: {exc})")
        return []


def quantisation_notes(outputs: OutputFit) -> list[str]:
    """A note for every measured output that is quantised: its step is noise, not an effect.

    Parameters
    ----------
    outputs : OutputFit
        The fitted outputs and the experiments' data.

    Returns
    -------
    list of str
        One note per quantised output, with its step and the variance step²/12.
    """
    notes = []
    for j, name in enumerate(outputs.names):
        measured = measured_values(outputs, j)
        step = quantisation_step(measured) if measured.size else None
        if step is not None:
            notes.append(f"output {name} is quantised in steps of {fmt(step)}: treated as noise "
                         f"(variance step²/12 = {fmt(step ** 2 / 12)}), not as an effect")
    return notes


def drop_duplicates(cands: list[Candidate]) -> list[Candidate]:
    """The later of two single-column candidates of the same equations whose columns are equal up
    to scale (|correlation| ≈ 1) goes: the same hypothesis proposed twice is counted once.

    Parameters
    ----------
    cands : list of Candidate
        The candidates in registry order.

    Returns
    -------
    list of Candidate
        The same in the same order without the later duplicates; candidates on outputs, with data
        transforms or with multi-column regressors are always kept.
    """
    columns = [_column(c) for c in cands]
    groups: dict[tuple, list[int]] = {}
    for k, (c, col) in enumerate(zip(cands, columns)):
        if col is not None:
            groups.setdefault((tuple(sorted(c.equations)), col.size), []).append(k)
    dropped: set[int] = set()
    for members in groups.values():
        if len(members) < 2:
            continue
        block = np.vstack([cast(np.ndarray, columns[k]) for k in members])
        norms = np.linalg.norm(block, axis=1)
        unit = block / np.where(norms > 0, norms, 1.0)[:, None]
        same = np.abs(unit @ unit.T) > SAME_COLUMN
        kept_here: list[int] = []
        for i, k in enumerate(members):
            if norms[i] == 0:      # no direction: kept, and never anyone's duplicate
                continue
            if any(same[i, j] for j in kept_here):
                dropped.add(k)
            else:
                kept_here.append(i)
    return [c for k, c in enumerate(cands) if k not in dropped]


def _column(c: Candidate) -> np.ndarray | None:
    """The candidate's single column over its equations, non-finite entries 0; None when it is not
    one column on equations (on outputs, with data transforms, several columns)."""
    if c.outputs or not c.equations or c.transform_experiments is not None:
        return None
    parts = [np.asarray(col, dtype=float) for eq in sorted(c.equations) for col in c.equations[eq]]
    if any(p.ndim != 1 for p in parts):
        return None
    vec = parts[0] if len(parts) == 1 else np.concatenate(parts)
    return np.where(np.isfinite(vec), vec, 0.0)
