"""The two batch families behind one interface: equation error and output error (shooting).

`fit_model` builds one of these through the registry (`solvers.methods.registry`) and then only
asks it questions: solve from these starts, the Jacobian for the covariance, the residual per
reported channel, the initial states. What differs between the families lives here, once.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Literal, Protocol

import numpy as np

from greyfit.schemas.fit import FitMethod, FitOptions, MethodChoice
from greyfit.solvers.data.experiments import ExperimentData
from greyfit.solvers.methods.equation_error import EquationErrorProblem, build_equation_error
from greyfit.solvers.methods.method_choice import choose_shooting
from greyfit.solvers.methods.multistart import MultistartRun, exact_form, solve_from_starts
from greyfit.solvers.methods.shooting import (
    OutputErrorModel,
    build_multiple_shooting,
    build_single_shooting,
    sensitivity_jacobian,
)
from greyfit.solvers.model.compiler import CompiledModel
from greyfit.solvers.model.parameters import ParameterLayout
from greyfit.solvers.nlp.problem import LeastSquaresProblem
from greyfit.solvers.nlp.solver import NlpOutcome


@dataclass
class Residuals:
    """Unweighted residual (model − measured) and measured signal per reported channel."""

    channels: list[str]
    per_experiment: list[tuple[np.ndarray, np.ndarray]]  # (measured, residual), each (nch, N)
    states: list[np.ndarray] | None = None   # simulated states per experiment (output error)


@dataclass
class Jacobian:
    """What the covariance needs: J and r at the solution, the columns' labels, values, scales."""

    jac: np.ndarray
    res: np.ndarray
    groups: np.ndarray          # the residual row's channel (for per-channel noise variances)
    labels: list[str]
    values: np.ndarray
    scale: np.ndarray
    n_extra: int                # columns past the parameters (free initial states)


class BatchFit(Protocol):
    """A method's built problem, as `fit_model` uses it."""

    problem: LeastSquaresProblem
    data: list[ExperimentData]
    method: FitMethod                   # the method that runs (never auto)
    choice: MethodChoice | None         # set when auto chose `method`
    affine_solve: Callable | None       # equation error with a TV penalty: IRLS (batch extensions)
    eep: EquationErrorProblem | None    # set by equation error (checks read its rows)
    oem: OutputErrorModel | None        # set by output error (checks read its simulations)
    run: MultistartRun | None           # set by `solve` when it solved over the starts

    def solve(self, starts: list[np.ndarray], options: FitOptions,
              cpu0: float) -> tuple[NlpOutcome, int, bool | None]:
        """(best outcome, starts used, whether compiled C evaluated the model).

        Parameters
        ----------
        starts : list of numpy.ndarray
            Physical parameter vectors, the user's guess first (`draw_starts`).
        options : FitOptions
            The request's options.
        cpu0 : float
            The process time the fit began at; its preparation counts against ``max_cpu_time``.

        Returns
        -------
        outcome : NlpOutcome
            The best outcome over the starts.
        used : int
            The number of starts that ran.
        compiled : bool or None
            Whether compiled C evaluated the model (None when not known).
        """
        ...

    def jacobian(self, theta_s: np.ndarray, w: np.ndarray, x0s: list[dict[str, float]]) -> Jacobian:
        """J and r at the solution, as the covariance needs them.

        Parameters
        ----------
        theta_s : numpy.ndarray
            The scaled free parameters at the solution, shape (n θ,).
        w : numpy.ndarray
            The NLP's full decision vector at the solution.
        x0s : list of dict
            Per experiment, state name -> initial value at the solution.

        Returns
        -------
        Jacobian
            The Jacobian, the weighted residual, each row's channel, and the columns' labels, values and scales.
        """
        ...

    def channels(self, theta: np.ndarray, x0s: list[dict[str, float]], res: np.ndarray) -> Residuals:
        """The unweighted residual and the measured signal per reported channel.

        Parameters
        ----------
        theta : numpy.ndarray
            The physical free parameters at the solution, shape (n θ,).
        x0s : list of dict
            Per experiment, state name -> initial value at the solution.
        res : numpy.ndarray
            The weighted residual at the solution (`Jacobian.res`).

        Returns
        -------
        Residuals
            Channel names and, per experiment, (measured, residual), each of shape (n channels, N).
        """
        ...

    def initial_states(self, x0s: list[dict[str, float]]) -> dict[str, dict[str, float]]:
        """The initial states to report, per experiment.

        Parameters
        ----------
        x0s : list of dict
            Per experiment, state name -> initial value at the solution.

        Returns
        -------
        dict
            Experiment name -> (state name -> initial value).
        """
        ...

    def solver_details(self) -> dict:
        """Fields of `SolverInfo` only this family knows.

        Returns
        -------
        dict
            ``derivative_filter`` and ``linear_in_parameters``.
        """
        ...


class EquationErrorFit:
    """Residual ẋ_measured − f(x, u, θ) on measured (or smoothed) states and derivatives."""

    oem: OutputErrorModel | None = None
    run: MultistartRun | None = None
    method = FitMethod.equation_error
    choice: MethodChoice | None = None

    def __init__(self, eep: EquationErrorProblem, data: list[ExperimentData], cm: CompiledModel,
                 layout: ParameterLayout):
        self.eep, self.problem, self.data, self.cm, self.layout = eep, eep.problem, data, cm, layout
        self.affine_solve: Callable | None = None   # set by the batch extensions (IRLS for TV)

    @classmethod
    def build(cls, cm: CompiledModel, data: list[ExperimentData], layout: ParameterLayout,
              options: FitOptions) -> "EquationErrorFit":
        """Build the equation-error problem (`build_equation_error`).

        Parameters
        ----------
        cm : CompiledModel
            The compiled model; every state must be measured directly.
        data : list of ExperimentData
            The prepared experiments.
        layout : ParameterLayout
            The free parameters and their mapping to each experiment.
        options : FitOptions
            Derivative window and order, and input interpolation.

        Returns
        -------
        EquationErrorFit
            The built fit.

        Raises
        ------
        DataError
            When a state is not measured, no sample is usable, or no equation depends on a free parameter.
        """
        return cls(build_equation_error(cm, data, layout, options), data, cm, layout)

    def solve(self, starts, options, cpu0):
        """Solve by IRLS (affine residual with a TV penalty), the closed form (linear), or from every
        start; `compiled` is None after IRLS."""
        if self.affine_solve is not None:
            affine = self.affine_solve(self.problem, self.layout, self.eep.linear)
            if affine:
                return (*affine, None)
        self.run = solve_from_starts(self.problem, options, starts,
                                     self.eep.linear and self.problem.penalty is None, cpu0)
        outcome, used, is_c = self.run.best, self.run.used, self.run.compiled
        if outcome.status == "Linear_Least_Squares":   # the per-sample Jacobian was all that ran
            is_c = self.eep.sample.compiled
        return outcome, used, is_c

    def jacobian(self, theta_s, w, x0s):
        """J and r of the equation-error residual at the solution, one row group per used equation, no
        extra columns (`x0s` is not used: equation error estimates no initial state)."""
        jac, res = self.problem.evaluate_jacobian(w)
        groups = np.concatenate([np.tile(np.arange(len(self.eep.equations)), ed.rows.size)
                                 for ed in self.eep.per_experiment])
        return Jacobian(jac, res, groups, list(self.layout.labels), self.layout.physical(theta_s),
                        self.layout.scale, 0)

    def channels(self, theta, x0s, res):
        """The solver's own weighted residual `res`, unweighted, per derivative ``der(state)`` of the used
        equations, NaN at the rows not used (`theta` and `x0s` are not used)."""
        eep, per, start = self.eep, [], 0
        neq = len(eep.equations)
        w = eep.weights[eep.equations][:, None]
        for e, d in enumerate(self.data):
            ed = eep.per_experiment[e]
            block = res[start:start + neq * ed.rows.size].reshape(ed.rows.size, neq).T
            start += neq * ed.rows.size
            meas = np.full((neq, d.n), np.nan)
            resid = np.full((neq, d.n), np.nan)
            meas[:, ed.rows] = ed.dx[eep.equations][:, ed.rows]
            resid[:, ed.rows] = -block / w
            per.append((meas, resid))
        return Residuals([f"der({self.cm.states[i]})" for i in eep.equations], per)

    def initial_states(self, x0s):
        """The measured (or smoothed) states at each experiment's first usable row (`x0s` is not used)."""
        per = self.eep.per_experiment
        return {d.name: {s: float(per[e].x[i, per[e].rows[0]]) for i, s in enumerate(self.cm.states)}
                for e, d in enumerate(self.data)}

    def solver_details(self):
        """The derivative filter's note (``derivative_filter``) and whether the residual is linear in the
        parameters (``linear_in_parameters``)."""
        return {"derivative_filter": self.eep.derivative_filter, "linear_in_parameters": self.eep.linear}


class OutputErrorFit:
    """Residual y_simulated − y_measured; single shooting (one simulation per record) or multiple
    shooting (nodes as decision variables, gaps as constraints)."""

    eep: EquationErrorProblem | None = None
    affine_solve: Callable | None = None
    run: MultistartRun | None = None

    def __init__(self, oem: OutputErrorModel, problem: LeastSquaresProblem,
                 builder: Callable[[OutputErrorModel], LeastSquaresProblem], method: FitMethod,
                 choice: MethodChoice | None = None):
        self.oem, self.problem, self.data, self.builder = oem, problem, oem.data, builder
        self.method, self.choice = method, choice

    @classmethod
    def build(cls, cm: CompiledModel, data: list[ExperimentData], layout: ParameterLayout,
              options: FitOptions, shooting: Literal["single", "multiple", "auto"]) -> "OutputErrorFit":
        """Build the output-error model and its single- or multiple-shooting problem (auto: the one
        `method_choice.choose_shooting` picks from a simulation at the start guess).

        Parameters
        ----------
        cm : CompiledModel
            The compiled model.
        data : list of ExperimentData
            The prepared experiments.
        layout : ParameterLayout
            The free parameters and their mapping to each experiment.
        options : FitOptions
            The request's options (integrator, Hessian, weights, ...).
        shooting : {"single", "multiple", "auto"}
            One simulation per record, nodes as decision variables with continuity constraints, or
            the first where the model can be simulated from the start guess, else the second.

        Returns
        -------
        OutputErrorFit
            The built fit, keeping its builder for the exact-Hessian polish, and the choice (auto).
        """
        oem = OutputErrorModel(cm, data, layout, options)
        choice = choose_shooting(oem) if shooting == "auto" else None
        if choice is not None:
            shooting = "single" if choice.ran == FitMethod.single_shooting else "multiple"
        builder = build_single_shooting if shooting == "single" else build_multiple_shooting
        method = FitMethod.single_shooting if shooting == "single" else FitMethod.multiple_shooting
        return cls(oem, builder(oem), builder, method, choice)

    def solve(self, starts, options, cpu0):
        """Solve from every start; the best is polished with the exact Hessian when none converged."""
        # the exact form: the polish of a fit Gauss-Newton did not converge (multistart.py)
        self.run = solve_from_starts(self.problem, options, starts, False, cpu0,
                                     exact_form(self.builder, self.oem, self.problem))
        return self.run.best, self.run.used, self.run.compiled

    def jacobian(self, theta_s, w, x0s):
        """Sensitivities of the simulated outputs at the solution: for multiple shooting the nodes
        are eliminated this way (its gaps are zero there); the free initial states are the `n_extra`
        columns after the parameters."""
        oem, cm = self.oem, self.oem.cm
        theta = oem.layout.physical(theta_s)
        x0_free = [x0s[e][cm.states[i]] / oem.xscale[i] for e, f in enumerate(oem.free_x0) for i in f]
        x0_scale = [oem.xscale[i] for f in oem.free_x0 for i in f]
        jac, res, groups = sensitivity_jacobian(oem, theta_s, x0s, w)
        return Jacobian(jac, res, groups, list(oem.layout.labels) + oem.x0_labels(),
                        np.concatenate([theta, np.array(x0_free) * np.array(x0_scale, dtype=float)]),
                        np.concatenate([oem.layout.scale, x0_scale]), len(x0_free))

    def channels(self, theta, x0s, res):
        """Simulate at the solution: residual (simulated − measured) per output, and the simulated states
        (`res` is not used: the residual is simulated again, unweighted)."""
        cm, data = self.oem.cm, self.oem.data
        sims = self.oem.simulate(theta, [np.array([x0s[e][s] for s in cm.states]) for e in range(len(data))])
        per = [(d.y, ys - d.y) for d, (_, ys) in zip(data, sims)]
        return Residuals(list(cm.outputs), per, [xs for xs, _ in sims])

    def initial_states(self, x0s):
        """The initial states at the solution, per experiment."""
        return {d.name: x0s[e] for e, d in enumerate(self.oem.data)}

    def solver_details(self):
        """No derivative filter, no linearity flag: output error has neither (both None)."""
        return {"derivative_filter": None, "linear_in_parameters": None}
