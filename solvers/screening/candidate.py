"""A candidate term of the effect library, and what a family generates it from.

A `Candidate` is one term a family proposes: its regressor per equation (or per output), the term as
the report shows it, and how it rewrites the model (`apply`, bound to its family's `rewrite`).
`LibraryContext` is everything a family reads: the model, the fitted trajectory (`TraceData`), the
options, and the fitted outputs when the output path is screened.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from greyfit.schemas.discovery import CustomCandidate
from greyfit.schemas.model import Model
from greyfit.solvers.data.experiments import ExperimentData
from greyfit.solvers.screening.canonical import canonical_form
from greyfit.solvers.screening.scoring_equations import TraceData

Regressor = dict[int, list[np.ndarray]]
Rewrite = Callable[[Model], tuple[Model, list[str]]]


@dataclass
class Candidate:
    effect: str
    equations: Regressor                      # equation index -> regressor per experiment
    term: str                                 # the term as it enters the model (for the report)
    description: str
    apply: Rewrite                            # -> augmented model, new parameter names
    sign: float = 0.0          # +1/-1: the coefficient must have this sign to be physical; 0: any
    family: str = ""           # scanned variants of one candidate share a family (Bonferroni counts them)
    stiffness: float = 0.0     # |∂(term)/∂x| per unit coefficient: tanh(v/ε) adds |β|/ε to the Jacobian
    refit_variants: bool = False   # let the confirming refit choose among the family's variants
    tries: int = 1             # alternatives this candidate was selected from (counts for Bonferroni)
    transform_experiments: Callable | None = None   # data the new model needs (a delayed input)
    outputs: Regressor | None = None   # direct effect on outputs (output-path effects)
    record_specific: bool = False   # a step or drift in time: true of this record, not of new data
    key: str = ""              # identifies the same term found by either scorer
    refit_only: bool = False   # its linearisation at this fit says nothing (e.g. |h| where h > 0): refit decides
    fresh_start: bool = False  # refit from the declared initial values, not from the fit it replaces
    generic: bool = False      # a catch-all shape (a switching coefficient, a shift in time), not a named law
    # hypotheses behind the candidate beyond `tries`: a set of switch times chosen jointly from a grid is
    # one of C(grid, m) subsets, not one of grid·m columns; its p-value is multiplied by this
    multiplicity: float = 1.0
    width: float = 0.0         # the ε of a smoothed switch tanh(v/ε): its variants differ only in it
    lag: int = 0               # a delay's whole samples: its variants differ only in it (the refit walks along it)
    modifies: str = ""         # the declared parameter a time- or state-varying law changes (parsimony checks)
    variables: tuple[str, ...] = ()   # the states and inputs the term is a function of (what would separate it)
    # a member of a series that approximates many laws (a power, a smooth p(x)), not a law named for a
    # mechanism: refitted beside the named laws within the margin, never instead of them
    approximating: bool = False
    # structural values chosen by search and not refitted as parameters (a step's switch times): each
    # counts as a parameter when refits with different numbers of them are compared by BIC
    searched: int = 0

    def __post_init__(self):
        self.key = self.key or f"{self.family}|{self.term}"

    @property
    def catch_all(self) -> bool:
        """A generic shape or a change in time: kept only where no named law does as well.

        Returns
        -------
        bool
            True when the candidate is `generic` or `record_specific`.
        """
        return self.generic or self.record_specific

    def same_place(self, other: Candidate) -> bool:
        """Whether the two act on a common equation or output.

        Parameters
        ----------
        other : Candidate
            The other candidate.

        Returns
        -------
        bool
            True when they share a state equation or an output.
        """
        return bool(set(self.equations) & set(other.equations)) or \
            bool(set(self.outputs or {}) & set(other.outputs or {}))


@dataclass
class OutputFit:
    """The fitted outputs, for the families that act in the output path."""

    names: list[str]
    fitted: list[np.ndarray]          # per experiment, (ny, n)
    data: list[ExperimentData]


@dataclass
class LibraryContext:
    """What a family generates its candidates from (see `families.Family`)."""

    model: Model
    trace: TraceData
    effects: list[str]
    custom: list[CustomCandidate] = field(default_factory=list)
    epsilon: float | None = None
    scorer_for: Callable | None = None
    significance: float = 0.01
    min_explained: float = 0.05
    outputs: OutputFit | None = None
    notes: list[str] = field(default_factory=list)

    def __post_init__(self):
        self.pos_of, self.vel_of = structure(self.model)

    @property
    def states(self) -> list[str]:
        """The model's state names, in the compiled order.

        Returns
        -------
        list of str
            The state names.
        """
        return list(self.trace.cm.states)

    @property
    def velocities(self) -> list[str]:
        """States that are the velocity of a position (dx/dt = v); all states when there are none.

        Returns
        -------
        list of str
            The velocity states, or every state.
        """
        return [s for s in self.states if s in self.pos_of] or self.states

    def state_values(self, s: str) -> list[np.ndarray]:
        """Fitted samples of one state.

        Parameters
        ----------
        s : str
            The state's name.

        Returns
        -------
        list of numpy.ndarray
            One (n_e,) array per experiment.
        """
        return [x[self.states.index(s)] for x in self.trace.x]

    def input_values(self, u: str) -> list[np.ndarray]:
        """Samples of one input along the trace.

        Parameters
        ----------
        u : str
            The input's name.

        Returns
        -------
        list of numpy.ndarray
            One (n_e,) array per experiment.
        """
        k = list(self.trace.cm.inputs).index(u)
        return [uu[k] for uu in self.trace.u]

    def values(self, name: str) -> list[np.ndarray]:
        """Samples of a state, an input or a constant, per experiment.

        Parameters
        ----------
        name : str
            A state, input or constant of the model.

        Returns
        -------
        list of numpy.ndarray
            One (n_e,) array per experiment (a constant repeated over the samples).
        """
        if name in self.states:
            return self.state_values(name)
        if name in self.trace.cm.inputs:
            return self.input_values(name)
        c = float(self.model.constants[name])
        return [np.full(t.size, c) for t in self.trace.t]

    def traced(self, s: str) -> bool:
        """Whether the equation of state `s` is traced (has a fitted derivative to regress on).

        Parameters
        ----------
        s : str
            The state's name.

        Returns
        -------
        bool
            True when its index is in `trace.traced`.
        """
        return self.states.index(s) in set(self.trace.traced)

    def equation_variables(self, eq: str) -> list[str]:
        """States and inputs d(eq)/dt depends on along the trajectory (its own state always): a law
        that enters an equation is a law of what that equation already involves.

        Parameters
        ----------
        eq : str
            The state whose equation is looked at.

        Returns
        -------
        list of str
            The states (its own always, in model order) and then the inputs whose Jacobian entries are
            nonzero somewhere along the trajectory.
        """
        i = self.states.index(eq)
        cm = self.trace.cm
        names = [s for k, s in enumerate(self.states)
                 if k == i or any(np.any(j[:, i, k] != 0) for j in self.trace.jx)]
        return names + [u for k, u in enumerate(cm.inputs) if any(np.any(j[:, i, k] != 0) for j in self.trace.ju)]

    def force_equations(self) -> list[str]:
        """Traced equations that are not kinematic identities dx/dt = v (those have no force to add to).

        Returns
        -------
        list of str
            The state names of those equations.
        """
        return [s for s in self.states if self.traced(s) and s not in self.vel_of]


def fmt(v: float) -> str:
    """A number as it is written into a model expression (6 significant digits).

    Parameters
    ----------
    v : float
        The number.

    Returns
    -------
    str
        ``f"{v:.6g}"``.
    """
    return f"{v:.6g}"


def structure(model: Model) -> tuple[dict[str, str], dict[str, str]]:
    """(velocity -> its position, position -> its velocity) from kinematic equations dx/dt = v.

    Parameters
    ----------
    model : Model
        The model; an equation that means exactly another state (`v`, `1*v`, `--v`) is kinematic
        (`canonical.canonical_form`).

    Returns
    -------
    tuple of dict of str to str
        (pos_of: velocity -> position, vel_of: position -> velocity).

    Raises
    ------
    ModelDefinitionError
        When an equation does not compile.
    """
    form = canonical_form(model)
    return dict(form.pos_of), dict(form.vel_of)
