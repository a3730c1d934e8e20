"""What every least-squares solver offers the fit pipeline (plain, structured and hybrid alike)."""
from __future__ import annotations

from typing import Protocol

import numpy as np

from greyfit.solvers.nlp.solver import NlpOutcome


class Solver(Protocol):
    """Solves one NLP from a start; `compiled` says whether generated C evaluated the model."""

    compiled: bool

    def solve(self, w0: np.ndarray, lbw: np.ndarray | None = None,
              ubw: np.ndarray | None = None) -> NlpOutcome:
        """The outcome from start `w0` (bounds default to the problem's).

        Parameters
        ----------
        w0 : numpy.ndarray
            Start decision vector, shape (n_w,).
        lbw, ubw : numpy.ndarray or None, optional
            Lower and upper bounds on w, shape (n_w,); None uses the problem's bounds.

        Returns
        -------
        NlpOutcome
            The solution, cost, solver status, success flag, iterations and wall time.
        """
        ...


class SolverFactory(Protocol):
    """Builds a solver over another formulation of the same NLP (structured multiple shooting).

    `max_iter`, `max_cpu_time`: instead of the request's (a phase of a hybrid solve).
    """

    def __call__(self, max_iter: int | None = None, max_cpu_time: float | None = None) -> Solver:
        ...
