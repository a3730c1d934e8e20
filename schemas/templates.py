"""Linear state-space templates (MATLAB idgrey style) expanded into the ODE contract.

    dx/dt = A x + B u,   y = C x + D u

Entries are numbers, parameter names or expressions. The expansion is plain text building (no
numerics), done when the model is validated, so every later stage sees ordinary equations.
"""
from __future__ import annotations

from typing import Optional, Union

from pydantic import BaseModel, ConfigDict, Field

Entry = Union[float, str]


class LinearStateSpace(BaseModel):
    model_config = ConfigDict(extra="forbid")

    A: list[list[Entry]] = Field(description="states × states")
    B: Optional[list[list[Entry]]] = Field(default=None, description="states × inputs")
    C: Optional[list[list[Entry]]] = Field(default=None, description="outputs × states; default: every state")
    D: Optional[list[list[Entry]]] = Field(default=None, description="outputs × inputs")
    output_names: Optional[list[str]] = Field(default=None, description="default y1, y2, ...")


def _check(matrix, rows: int, cols: int, name: str, row_what: str, col_what: str) -> None:
    if len(matrix) != rows:
        raise ValueError(f"linear_state_space.{name}: {len(matrix)} rows, {row_what} has {rows}")
    for i, row in enumerate(matrix):
        if len(row) != cols:
            raise ValueError(f"linear_state_space.{name}[{i}]: {len(row)} entries, {col_what} has {cols}")


def _term(entry: Entry, name: str) -> str | None:
    if isinstance(entry, (int, float)):
        if entry == 0:
            return None
        return name if entry == 1 else f"({entry!r})*{name}"
    text = entry.strip()
    if text in ("0", "0.0"):
        return None
    return f"({text})*{name}"


def _row(entries: list[Entry], names: list[str]) -> str:
    terms = [t for t in (_term(e, n) for e, n in zip(entries, names)) if t is not None]
    return " + ".join(terms) if terms else "0"


def expand_linear_state_space(lss: LinearStateSpace, states: list[str], inputs: list[str],
                              ) -> tuple[dict[str, str], Optional[dict[str, str]]]:
    """(equations, outputs) of ẋ = Ax + Bu, y = Cx + Du; outputs None means every state measured."""
    nx, nu = len(states), len(inputs)
    _check(lss.A, nx, nx, "A", "states", "states")
    if lss.B is not None:
        _check(lss.B, nx, nu, "B", "states", "inputs")
    equations = {}
    for i, s in enumerate(states):
        parts = [_row(lss.A[i], states)]
        if lss.B is not None:
            parts.append(_row(lss.B[i], inputs))
        parts = [p for p in parts if p != "0"]
        equations[s] = " + ".join(parts) if parts else "0"
    if lss.C is None:
        if lss.D is not None:
            raise ValueError("linear_state_space.D: give C too (D alone has no outputs to add to)")
        return equations, None
    ny = len(lss.C)
    _check(lss.C, ny, nx, "C", "C", "states")
    if lss.D is not None:
        _check(lss.D, ny, nu, "D", "C", "inputs")
    names = lss.output_names or [f"y{i + 1}" for i in range(ny)]
    if len(names) != ny:
        raise ValueError(f"linear_state_space.output_names: {len(names)} names for {ny} rows of C")
    outputs = {}
    for i, name in enumerate(names):
        parts = [_row(lss.C[i], states)] + ([_row(lss.D[i], inputs)] if lss.D is not None else [])
        parts = [p for p in parts if p != "0"]
        outputs[name] = " + ".join(parts) if parts else "0"
    return equations, outputs
