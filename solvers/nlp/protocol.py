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
        """The outcome from start `w0` (bounds default to the problem's)."""
        ...
