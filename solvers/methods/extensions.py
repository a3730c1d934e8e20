"""What the online-estimation issue adds to batch fits, applied in one place by `fit_model`:
discrete-time sampling checks, prefilters and time-varying parameters."""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from greyfit.schemas.fit import FitRequest, FitResult
from greyfit.schemas.model import Model
from greyfit.solvers.data.experiments import ExperimentData
from greyfit.solvers.data.prefilter import apply_prefilter
from greyfit.solvers.errors import DataError
from greyfit.solvers.methods.registry import simulates_outputs
from greyfit.solvers.model.compiler import CompiledModel
from greyfit.solvers.model.discrete import armax_start, check_sample_time, is_discrete
from greyfit.solvers.model.parameters import ParameterLayout
from greyfit.solvers.model.time_varying import IRLS_STATUS, TimeVaryingExpansion, expand_time_varying


@dataclass
class BatchExtensions:
    cm: CompiledModel
    data: list[ExperimentData]
    model: Model                         # the model the parameter layout is built from
    varying: TimeVaryingExpansion | None
    note: str | None

    def attach(self, problem, layout: ParameterLayout) -> None:
        """Add the total-variation rows to the problem (before it is solved).

        Parameters
        ----------
        problem : LeastSquaresProblem
            The fit's NLP; its `penalty` is set when time-varying parameters are declared.
        layout : ParameterLayout
            Layout of the (expanded) parameters.

        Returns
        -------
        None
        """
        if self.varying is not None:
            problem.penalty = self.varying.penalty(layout)

    def solve_affine(self, problem, layout: ParameterLayout, affine: bool):
        """(outcome, starts) by IRLS when the residual is affine and a TV penalty is declared, else None.

        Parameters
        ----------
        problem : LeastSquaresProblem
            The fit's NLP.
        layout : ParameterLayout
            Layout of the (expanded) parameters.
        affine : bool
            True when the residual is affine in the scaled θ.

        Returns
        -------
        tuple of (NlpOutcome, int) or None
            The IRLS outcome and the number of starts used; None when the residual is not affine,
            no time-varying parameter is declared, or IRLS declines (a bound violated, no penalty).
        """
        if not affine or self.varying is None:
            return None
        return self.varying.solve_affine(problem, layout)

    def finish(self, result: FitResult, layout: ParameterLayout, theta: np.ndarray, cov) -> FitResult:
        """Trajectory of the time-varying parameters and the prefilter note.

        Parameters
        ----------
        result : FitResult
            The fit's result; changed in place.
        layout : ParameterLayout
            Layout of the (expanded) parameters.
        theta : numpy.ndarray
            The estimated free parameters.
        cov : object
            The covariance, with `names` and `matrix`, used for the trajectory's uncertainty.

        Returns
        -------
        FitResult
            `result`, with the prefilter note added to `solver.derivative_filter`, the IRLS message,
            and the `trajectory` of the time-varying parameters when there are any.
        """
        if self.note:
            result.solver.derivative_filter = "; ".join(x for x in (result.solver.derivative_filter, self.note) if x)
        if result.solver.return_status == IRLS_STATUS:
            result.message = (f"solved by iteratively reweighted least squares in {result.solver.iterations} "
                              "iterations (affine residual plus total-variation penalty)")
        if self.varying is not None:
            times = np.unique(np.concatenate([d.t for d in self.data]))
            result.trajectory = self.varying.trajectory(layout, theta, cov.names, cov.matrix, times)
        return result


def prepare_batch(request: FitRequest, cm: CompiledModel, data: list[ExperimentData]) -> BatchExtensions:
    """Apply the batch extensions before a fit: sample-time check, prefilter, ARMAX start, time-varying expansion.

    Parameters
    ----------
    request : FitRequest
        The fit request (model, method and options).
    cm : CompiledModel
        The compiled model.
    data : list of ExperimentData
        The prepared experiments.

    Returns
    -------
    BatchExtensions
        The (possibly expanded) compiled model, the (possibly prefiltered) data, the model the layout
        is built from, the time-varying expansion or None, and the prefilter note or None.

    Raises
    ------
    DataError
        When a prefilter is requested with an output-error method (``options.prefilter``), or a
        discrete-time model's sample time does not match the data (``experiments[e].time``).
    """
    if is_discrete(cm):
        check_sample_time(cm, data)
    note = None
    if request.options.prefilter is not None:
        if simulates_outputs(request.method):
            raise DataError("a prefilter serves equation error and recursive least squares; output "
                            "error needs none (its residual is not built from noisy regressors)", "options.prefilter")
        data, note = apply_prefilter(cm, data, request.options.prefilter)
    model = armax_start(request.model, data)    # ARMAX templates: a, b from the ARX estimate
    varying = expand_time_varying(model, cm, data)
    if varying is not None:
        return BatchExtensions(varying.cm, data, varying.model, varying, note)
    return BatchExtensions(cm, data, model, None, note)
