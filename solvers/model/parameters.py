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
    def parameters(self) -> Sequence[Parameter]:
        """The declared parameters, in declaration order.

        Returns
        -------
        Sequence of Parameter
            Each with its name, value, bounds and whether it is fixed or per experiment.
        """
        ...


def nominal_scale(value: float, lower: float | None, upper: float | None) -> float:
    """A scale that brings the parameter to O(1) for the solver.

    Parameters
    ----------
    value : float
        The parameter's initial value.
    lower, upper : float or None
        Its bounds, None where there is none.

    Returns
    -------
    float
        |value| when non-zero, else the largest finite non-zero |bound|, else 1.
    """
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
        """Number of entries of θ (free parameters and per-experiment copies).

        Returns
        -------
        int
        """
        return len(self.labels)

    def physical(self, theta_scaled: np.ndarray) -> np.ndarray:
        """Physical values of the entries of θ.

        Parameters
        ----------
        theta_scaled : numpy.ndarray
            Scaled decision vector θ, shape (n_theta,).

        Returns
        -------
        numpy.ndarray
            θ times the scale, shape (n_theta,).
        """
        return np.asarray(theta_scaled).ravel() * self.scale

    def full(self, e: int, theta_scaled):
        """p_e as a numpy vector or a CasADi expression, depending on θ.

        Parameters
        ----------
        e : int
            Index of the experiment.
        theta_scaled : numpy.ndarray or casadi.MX or casadi.SX
            Scaled decision vector θ, n_theta entries.

        Returns
        -------
        numpy.ndarray or casadi expression
            ``offset + matrix[e] @ θ``: the full physical parameter vector of experiment e, np entries.
        """
        return self.offset + self.matrix[e] @ theta_scaled


def build_layout(model: DeclaresParameters, experiment_names: list[str]) -> ParameterLayout:
    """The layout of the free parameters of `model` over the experiments.

    Each free parameter is one entry of θ, or one per experiment where it is `per_experiment`
    (labelled ``name[experiment]``); fixed parameters enter as the constant offset.

    Parameters
    ----------
    model : DeclaresParameters
        Anything declaring `parameters` (an ODE model, a transfer function, a linearised model).
    experiment_names : list of str
        Names of the experiments, in order.

    Returns
    -------
    ParameterLayout
        Labels, scales, initial values and bounds (physical units) of θ, the fixed offset and one
        (np, n_theta) matrix per experiment.
    """
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
