"""The one place a fit method is named: `FitMethod` → the object that implements it.

Why: the method used to be decided again in the fit pipeline, inside the shooting builders and by
name comparisons in the checks, discovery and validation. Everything that depends on the method now
asks its entry here: `family` says what kind of residual it minimises (equation error compares
derivatives, output error simulates), `has_nodes` whether its solution is pieces joined at shooting
nodes, `build` makes its problem for `fit_model`, and online estimators run their own `fit`. Adding a
method is one class and one line in `METHODS`: what kind of entry it is (batch or online) is read from
the methods it has (the `BatchMethod` and `OnlineMethod` protocols, checked at run time), so neither
this module nor its test names the classes.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Literal, Protocol, runtime_checkable

from greyfit.schemas.fit import FitMethod, FitOptions, FitRequest, FitResult

if TYPE_CHECKING:
    from greyfit.solvers.data.experiments import ExperimentData
    from greyfit.solvers.methods.batch import BatchFit
    from greyfit.solvers.model.compiler import CompiledModel
    from greyfit.solvers.model.parameters import ParameterLayout

Family = Literal["equation_error", "output_error", "online", "frequency"]


@runtime_checkable
class MethodEntry(Protocol):
    """What every entry of `METHODS` says about its method (frequency-response fits have only this)."""

    @property
    def family(self) -> Family:
        """The kind of residual the method minimises.

        Returns
        -------
        Family
            'equation_error', 'output_error', 'online' or 'frequency'.
        """
        ...

    @property
    def has_nodes(self) -> bool:
        """Whether the solution is trajectory pieces joined at shooting nodes (multiple shooting).

        Returns
        -------
        bool
            True when the fitted pieces may fail to join into one simulation (a continuity gap).
        """
        ...


@runtime_checkable
class BatchMethod(MethodEntry, Protocol):
    """A method `fit_model` solves as one least-squares NLP over all records."""

    def build(self, cm: CompiledModel, data: list[ExperimentData], layout: ParameterLayout,
              options: FitOptions) -> BatchFit:
        """The method's problem, ready for the solver (see `solvers.methods.batch.BatchFit`).

        Parameters
        ----------
        cm : CompiledModel
            The compiled model.
        data : list of ExperimentData
            The prepared experiments.
        layout : ParameterLayout
            The free parameters, their scaling and their mapping to each experiment.
        options : FitOptions
            The request's options.

        Returns
        -------
        BatchFit
            The built problem with its solve, Jacobian and result hooks.
        """
        ...


@runtime_checkable
class OnlineMethod(MethodEntry, Protocol):
    """A method that runs over one record sample by sample and returns its own `FitResult`."""

    def fit(self, request: FitRequest) -> FitResult:
        """Estimate over the request's single experiment.

        Parameters
        ----------
        request : FitRequest
            The fit request, with one experiment.

        Returns
        -------
        FitResult
            The online estimator's result.
        """
        ...


@dataclass(frozen=True)
class _EquationError:
    family: Family = "equation_error"
    has_nodes: bool = False

    def build(self, cm, data, layout, options):
        from greyfit.solvers.methods.batch import EquationErrorFit
        return EquationErrorFit.build(cm, data, layout, options)


@dataclass(frozen=True)
class _OutputError:
    shooting: Literal["single", "multiple", "auto"]   # auto: solvers.methods.method_choice decides
    family: Family = "output_error"

    @property
    def has_nodes(self) -> bool:
        return self.shooting == "multiple"   # auto: not known before it has chosen

    def build(self, cm, data, layout, options):
        from greyfit.solvers.methods.batch import OutputErrorFit
        return OutputErrorFit.build(cm, data, layout, options, self.shooting)


@dataclass(frozen=True)
class _Online:
    family: Family = "online"
    has_nodes: bool = False

    def fit(self, request: FitRequest) -> FitResult:
        from greyfit.solvers.methods.online.estimate import fit_online
        return fit_online(request)


@dataclass(frozen=True)
class _Frequency:
    """Frequency-response fits take a `FrequencyFitRequest` (solvers.frequency); the entry is here
    so that every `FitMethod` has one and results can be asked about their family."""
    family: Family = "frequency"
    has_nodes: bool = False


METHODS: dict[FitMethod, MethodEntry] = {
    FitMethod.auto: _OutputError("auto"),
    FitMethod.equation_error: _EquationError(),
    FitMethod.single_shooting: _OutputError("single"),
    FitMethod.multiple_shooting: _OutputError("multiple"),
    FitMethod.recursive_least_squares: _Online(),
    FitMethod.mras: _Online(),
    FitMethod.frequency_response: _Frequency(),
}


def method_family(method: FitMethod | str) -> Family:
    """'equation_error', 'output_error', 'online' or 'frequency' for a method or its name.

    Parameters
    ----------
    method : FitMethod or str
        The method, or its value (e.g. ``"single_shooting"``).

    Returns
    -------
    Family
        The method's family.
    """
    return METHODS[FitMethod(method)].family


def simulates_outputs(method: FitMethod | str) -> bool:
    """Whether the method's residual is a simulation's (output error), not a derivative's.

    Parameters
    ----------
    method : FitMethod or str
        The method, or its value.

    Returns
    -------
    bool
        True for single and multiple shooting, and for auto (which runs one of them).
    """
    return method_family(method) == "output_error"


def has_shooting_nodes(method: FitMethod | str) -> bool:
    """Whether the method's solution is pieces joined at shooting nodes, not one simulation.

    Parameters
    ----------
    method : FitMethod or str
        The method, or its value.

    Returns
    -------
    bool
        True for multiple shooting only (auto has not chosen yet; a result names the method that ran).
    """
    return METHODS[FitMethod(method)].has_nodes


def batch_method(method: FitMethod) -> BatchMethod:
    """The batch implementation of `method` (TypeError for online and frequency methods).

    Parameters
    ----------
    method : FitMethod
        The method.

    Returns
    -------
    BatchMethod
        The entry that builds the method's least-squares problem.

    Raises
    ------
    TypeError
        When `method` is an online or frequency-response method (a programming error, not bad input).
    """
    entry = METHODS[method]
    if isinstance(entry, BatchMethod):   # structural: any entry with a `build`
        return entry
    raise TypeError(f"{method.value} is not a batch method")


def online_method(method: FitMethod) -> OnlineMethod | None:
    """The online implementation of `method`, None for batch and frequency methods.

    Parameters
    ----------
    method : FitMethod
        The method.

    Returns
    -------
    OnlineMethod or None
        The entry whose `fit` runs the online estimator; None for batch and frequency methods.
    """
    entry = METHODS[method]
    return entry if isinstance(entry, OnlineMethod) else None   # structural: any entry with a `fit`
