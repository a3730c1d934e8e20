"""What a family of effects is: the `Family` protocol, and the helpers most families build terms with.

A family says what it supports (`scope`, `generic`, `supports`), generates its candidates from the
fitted trajectory (`candidates`), and rewrites a model with one of them (`rewrite`, bound into each
candidate's `apply`). The loop calls them in that order: supports → candidates → (screen) → apply.
"""
from __future__ import annotations

from functools import partial
from typing import Any, Literal, Protocol, runtime_checkable

import numpy as np

from greyfit.schemas.model import Model
from greyfit.solvers.screening.augment import add_term, fresh_name, with_parameter
from greyfit.solvers.screening.candidate import Candidate, LibraryContext, Regressor
from greyfit.solvers.screening.canonical import canonical_form

# where a family's terms enter: a term in a state equation, a law of a declared parameter, a
# change of an input, or the output path (the sensor)
Scope = Literal["equation", "parameter", "input", "output"]


@runtime_checkable
class Family(Protocol):
    """One family of effects in the library (one module under `families/`, one line in the registry).

    Attributes
    ----------
    name : str
        The effect's name in `DiscoveryOptions.effects` (schemas/discovery.py checks it is listed).
    scope : Scope
        Where its terms enter the model.
    generic : bool
        A catch-all shape (a switching coefficient, a change in time, a delay) rather than a named
        physical law: kept only where no named law explains as much (`discriminate`).
    """

    name: str
    scope: Scope
    generic: bool

    def supports(self, ctx: LibraryContext) -> bool:
        """Whether the family can propose anything on this trace (e.g. the output path needs outputs).

        Parameters
        ----------
        ctx : LibraryContext
            The model, the fitted trajectory and the discovery options.

        Returns
        -------
        bool
            False when `candidates` would have nothing to look at.
        """
        ...

    def candidates(self, ctx: LibraryContext) -> list[Candidate]:
        """Its candidate terms on this trace, each with its regressor; notes go to `ctx.notes`.

        Parameters
        ----------
        ctx : LibraryContext
            The model, the fitted trajectory and the discovery options.

        Returns
        -------
        list of Candidate
            The family's candidates, each with `apply` bound to `rewrite` with its own spec.
        """
        ...

    def rewrite(self, model: Model, **spec: Any) -> tuple[Model, list[str]]:
        """`model` with the candidate described by `spec`, and the new parameters' names.

        Parameters
        ----------
        model : Model
            The model to augment (not changed: a copy is returned).
        **spec : Any
            What the candidate is (its equation, term, parameter stem, ...), as the family bound it.

        Returns
        -------
        tuple of (Model, list of str)
            The augmented model and the names of the parameters it added.
        """
        ...


def bind(family: "Family | TermFamily", **spec: Any):
    """A candidate's `apply`: the family's rewrite with the candidate's own spec.

    Parameters
    ----------
    family : Family or TermFamily
        The family whose `rewrite` is bound.
    **spec : Any
        The keyword arguments of that `rewrite`.

    Returns
    -------
    functools.partial
        ``model -> (augmented model, new parameter names)``.
    """
    return partial(family.rewrite, **spec)


def add_parameter_term(model: Model, *, equation: str, term: str, stem: str, sign: str,
                       lower: float | None) -> tuple[Model, list[str]]:
    """`sign p*term` added to d(equation)/dt with a new parameter p (start 0, or 1e-6 at a bound of 0).

    Parameters
    ----------
    model : Model
        The model to augment.
    equation : str
        The state whose equation gets the term.
    term : str
        The term's expression (model syntax), multiplied by the new parameter.
    stem : str
        Stem of the new parameter's name (made unique by `fresh_name`).
    sign : str
        "+" or "-": how the term enters the equation.
    lower : float or None
        Lower bound of the new parameter (start 1e-6 then); None: unbounded, start 0.

    Returns
    -------
    tuple of (Model, list of str)
        The augmented model and the one new parameter's name.

    Raises
    ------
    ModelDefinitionError
        When the equation does not parse.
    """
    name = fresh_name(model, stem)
    model = with_parameter(model, name, 0.0 if lower is None else 1e-6, lower=lower)
    return add_term(model, equation, f"{name}*{term}", sign), [name]


class NeedsTracedEquation:
    """The `supports` of a family whose columns are regressed on the traced state equations' fitted
    derivatives: it has something to look at when at least one equation is traced."""

    def supports(self, ctx: LibraryContext) -> bool:
        """Whether any state equation is traced (has a fitted derivative to regress on).

        Parameters
        ----------
        ctx : LibraryContext
            The model, the fitted trajectory and the discovery options.

        Returns
        -------
        bool
            True when the trace has at least one traced equation.
        """
        return bool(ctx.trace.traced)


class TermFamily(NeedsTracedEquation):
    """A family whose candidates are one term `sign p*term` in one state equation (subclasses
    provide `candidates`)."""

    name = ""
    scope: Scope = "equation"
    generic = False

    def rewrite(self, model: Model, **spec: Any) -> tuple[Model, list[str]]:
        """`model` with the term `sign p*term` in its equation (`add_parameter_term`).

        Parameters
        ----------
        model : Model
            The model to augment.
        **spec : Any
            `equation`, `term`, `stem`, `sign`, `lower` of `add_parameter_term`.

        Returns
        -------
        tuple of (Model, list of str)
            The augmented model and the new parameter's name.
        """
        return add_parameter_term(model, **spec)

    def term(self, ctx: LibraryContext, eq_state: str, regressor: list[np.ndarray], term: str, stem: str,
             sign: str, lower: float | None, description: str, phys_sign: float,
             variables: tuple[str, ...] = (), **extra: Any) -> Candidate | None:
        """The candidate `sign stem*term` in d(eq_state)/dt; None where that equation is not traced.

        A '-' term with a positive parameter contributes -g: the regression coefficient is on +g,
        so `phys_sign` is the sign the coefficient of +g must have.

        Parameters
        ----------
        ctx : LibraryContext
            The model and the fitted trajectory.
        eq_state : str
            The state whose equation gets the term.
        regressor : list of numpy.ndarray
            The term's samples g(t), one (n_e,) array per experiment.
        term : str
            The term's expression (model syntax).
        stem : str
            Stem of the new parameter's name.
        sign : str
            "+" or "-": how the term enters the equation.
        lower : float or None
            Lower bound of the new parameter; None: unbounded.
        description : str
            What the term is, for the report.
        phys_sign : float
            +1/−1: the sign the regression coefficient must have to be physical; 0: any.
        variables : tuple of str
            The states and inputs the term is a function of.
        **extra : Any
            Further `Candidate` fields (e.g. `stiffness`, `tries`).

        Returns
        -------
        Candidate or None
            The candidate (family ``name:eq_state``), or None where the equation is not traced.
        """
        if not ctx.traced(eq_state):
            return None
        eq = ctx.states.index(eq_state)
        regs: Regressor = {eq: regressor}
        return Candidate(self.name, regs, f"{sign} {stem}*{term}", description,
                         bind(self, equation=eq_state, term=term, stem=stem, sign=sign, lower=lower),
                         sign=phys_sign, family=f"{self.name}:{eq_state}", generic=self.generic,
                         variables=variables, **extra)


def sensitivity_regressor(trace, jacobians: list[np.ndarray], j: int, change: list[np.ndarray]) -> Regressor:
    """∂f_i/∂z_j · change(t) for every traced equation that depends on z_j (a parameter or input).

    Parameters
    ----------
    trace : TraceData
        The fitted trajectory; its `traced` equations are looked at.
    jacobians : list of numpy.ndarray
        Per experiment, (n_e, nx, nz) Jacobians ∂f/∂z along the trajectory.
    j : int
        Index of z_j in them.
    change : list of numpy.ndarray
        Per experiment, (n_e,) the change of z_j in time.

    Returns
    -------
    Regressor
        Equation index -> one column per experiment, for the equations where a column is not all zero.
    """
    reg = {}
    for i in trace.traced:
        cols = [jac[:, i, j] * c for jac, c in zip(jacobians, change)]
        if any(np.any(c != 0) for c in cols):
            reg[i] = cols
    return reg


def param_regressor(trace, j: int, shape: list[np.ndarray]) -> Regressor:
    """The column of a parameter θ_j that varies as θ_j + β·shape(t): ∂f/∂θ_j · shape.

    Parameters
    ----------
    trace : TraceData
        The fitted trajectory (its parameter Jacobians `jp`).
    j : int
        Index of the parameter in the model's parameter vector.
    shape : list of numpy.ndarray
        Per experiment, (n_e,) the shape of the change.

    Returns
    -------
    Regressor
        Equation index -> one column per experiment (`sensitivity_regressor`).
    """
    return sensitivity_regressor(trace, trace.jp, j, shape)


def shared_free(model: Model) -> list[str]:
    """Declared parameters a law in a state or in time can act on (free, one value for all records).

    Parameters
    ----------
    model : Model
        The model.

    Returns
    -------
    list of str
        Names of the parameters that are neither fixed nor per-experiment, in declaration order.
    """
    return [p.name for p in model.parameters if not p.fixed and not p.per_experiment]


def declared_differences(model: Model) -> list[tuple[str, str, str]]:
    """(equation, a, b) for every difference a − b a state equation acts on: a relative speed
    v4 − wd, a temperature difference T − Ta, found by meaning (`canonical.canonical_form`), so
    `U*A*(Ta - T)` and `-U*A*(T - Ta)` give the same (T, Ta). Laws of such a difference (radiation
    T⁴ − Ta⁴, a damper that switches with |v4 − wd|) act on it.

    Parameters
    ----------
    model : Model
        The model; its state equations (definitions inlined) are read.

    Returns
    -------
    list of tuple of (str, str, str)
        (equation, a, b) for each distinct coupling, a the equation's own state or the pair's first
        state; b a state, an input or a constant.

    Raises
    ------
    ModelDefinitionError
        When an equation or definition does not compile.
    """
    return [(c.equation, c.a, c.b) for c in canonical_form(model).couplings]


def physical_variables(ctx: LibraryContext) -> set[str]:
    """Names whose samples a law may be a function of: states, inputs, constants.

    Parameters
    ----------
    ctx : LibraryContext
        The model and the fitted trajectory.

    Returns
    -------
    set of str
        The model's state, input and constant names.
    """
    return set(ctx.states) | set(ctx.trace.cm.inputs) | set(ctx.model.constants)


# a state "changes sign with substance" when at least this share of its samples lies beyond
# `SIGN_MARGIN` of its RMS on each side: a population that dips a hair below 0 as its fit starts does not
SIGN_SHARE = 0.05
SIGN_MARGIN = 0.05


def changes_sign(values: list[np.ndarray]) -> bool:
    """Whether a fitted state takes both signs with substance: at least `SIGN_SHARE` of its samples
    beyond ±`SIGN_MARGIN`·RMS on each side. A law of sign(x) (friction) acts only on such a state;
    on one that keeps its sign (a level, a concentration, a population) sign(x) is a constant.

    Parameters
    ----------
    values : list of numpy.ndarray
        The state's samples, one array per experiment.

    Returns
    -------
    bool
        True when both sides hold a material share of the samples.
    """
    allv = np.concatenate(values)
    rms = float(np.sqrt(np.mean(allv ** 2)))
    if rms == 0 or not np.isfinite(rms):
        return False
    margin = SIGN_MARGIN * rms
    return min(float(np.mean(allv > margin)), float(np.mean(allv < -margin))) >= SIGN_SHARE


def keeps_positive(values: list[np.ndarray]) -> bool:
    """Whether a fitted state is a positive quantity on these data: at most 1 % of its samples below
    −`SIGN_MARGIN`·RMS and most of them above +`SIGN_MARGIN`·RMS (a level, a concentration, a population).

    Parameters
    ----------
    values : list of numpy.ndarray
        The state's samples, one array per experiment.

    Returns
    -------
    bool
        True when the state is (essentially) nonnegative and mostly away from 0.
    """
    allv = np.concatenate(values)
    rms = float(np.sqrt(np.mean(allv ** 2)))
    if rms == 0 or not np.isfinite(rms):
        return False
    margin = SIGN_MARGIN * rms
    return float(np.mean(allv < -margin)) <= 0.01 and float(np.mean(allv > margin)) >= 0.5
