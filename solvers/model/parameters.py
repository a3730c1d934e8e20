"""Map the scaled decision vector to each experiment's physical parameter vector."""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from greyfit.schemas.model import Parameter


class DeclaresParameters(Protocol):
    """A model's declared parameters: an ODE `Model`, a transfer function or a linearised model."""

    @property
    def parameters(self) -> Sequence[Parameter]: ...


def nominal_scale(value: float, lower: float | None, upper: float | None) -> float:
    """A scale that brings the parameter to O(1) for the solver."""
    if value != 0:
        return abs(value)
    finite = [abs(b) for b in (lower, upper) if b is not None and math.isfinite(b) and b != 0]
    return max(finite) if finite else 1.0


@dataclass
class ParameterLayout:
    """Free parameters (shared or per-experiment copies) as a scaled decision vector θ.

    The physical parameters of experiment e are ``p_e = offset + matrix[e] @ θ``.
    """

    labels: list[str]            # result names: "k" or "offset[exp1]"
    base_names: list[str]        # declared parameter of each entry
    experiment: list[str | None]
    scale: np.ndarray
    initial: np.ndarray          # physical values
    lower: np.ndarray            # physical, -inf where none
    upper: np.ndarray
    offset: np.ndarray           # fixed parameters' values, zero elsewhere
    matrix: list[np.ndarray]     # one (np, nθ) per experiment
    fixed: dict[str, float]

    @property
    def size(self) -> int:
        return len(self.labels)

    def physical(self, theta_scaled: np.ndarray) -> np.ndarray:
        return np.asarray(theta_scaled).ravel() * self.scale

    def full(self, e: int, theta_scaled):
        """p_e as a numpy vector or a CasADi expression, depending on θ."""
        return self.offset + self.matrix[e] @ theta_scaled


def build_layout(model: DeclaresParameters, experiment_names: list[str]) -> ParameterLayout:
    names = [p.name for p in model.parameters]
    labels, base, exps, scale, init, lo, hi = [], [], [], [], [], [], [],
    offset = np.zeros(len(names))
    cols: list[tuple[int, int | None]] = []  # (parameter index, experiment index or None=all)
    fixed = {}
    for i, p in enumerate(model.parameters):
        if p.fixed:
            offset[i] = p.value
            fixed[p.name] = p.value
            continue
        copies = list(enumerate(experiment_names)) if p.per_experiment else [(None, None)]
        for e, ename in copies:
            labels.append(p.name if ename is None else f"{p.name}[{ename}]")
            base.append(p.name)
            exps.append(ename)
            scale.append(nominal_scale(p.value, p.lower, p.upper))
            init.append(p.value)
            lo.append(-np.inf if p.lower is None else p.lower)
            hi.append(np.inf if p.upper is None else p.upper)
            cols.append((i, e))
    matrices = []
    for e in range(len(experiment_names)):
        m = np.zeros((len(names), len(labels)))
        for j, (i, ee) in enumerate(cols):
            if ee is None or ee == e:
                m[i, j] = scale[j]
        matrices.append(m)
    return ParameterLayout(labels, base, exps, np.array(scale), np.array(init, dtype=float),
                           np.array(lo, dtype=float), np.array(hi, dtype=float), offset,
                           matrices, fixed)
