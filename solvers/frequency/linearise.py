"""An ODE model linearised at an operating point, as a transfer function of its parameters.

A = ∂f/∂x, B = ∂f/∂u, C = ∂h/∂x, D = ∂h/∂u are taken symbolically (CasADi) at the operating point,
and G(s) = C (sI − A)⁻¹ B + D is written as N(s)/det(sI − A) with the Faddeev–LeVerrier recursion

    M₁ = I,  c_{n−k} = −tr(A M_k)/k,  M_{k+1} = A M_k + c_{n−k} I,
    det(sI − A) = Σ c_k s^k (c_n = 1),   adj(sI − A) = Σ_{k=1..n} M_k s^{n−k},

so N(s) = C adj(sI − A) B + D det(sI − A) exactly. The result is an ordinary
`CompiledTransferFunction`: Levy start, costs, feedback loop, Routh–Hurwitz constraints (here on
det(sI − A), i.e. A's eigenvalues, or on the closed loop), multistart and the pole report all apply.

Operating point: with `equilibrium: "given"` the point is numbers and f(x0, u0, θ) = 0 is added to the
constraints as equalities. With `"solve"` the coefficients are expressions of (θ, x*) and x*(θ) comes
from a Newton rootfinder, so `arguments(p) = [p; x*(p)]` (CasADi differentiates x*(θ) by the implicit
function theorem).
"""
from __future__ import annotations

import casadi as ca
import numpy as np

from greyfit.schemas.frequency import LinearisedOdeModel
from greyfit.solvers.errors import DataError, ModelDefinitionError
from greyfit.solvers.frequency.polynomials import CompiledTransferFunction, Poly, _probe_points
from greyfit.solvers.model.compiler import CompiledModel, compile_model

MAX_LINEARISED_STATES = 20          # det/adj coefficients of larger A lose too many digits
EQUILIBRIUM_TOLERANCE = 1e-8        # |f| (relative to the point's scale) that counts as zero


def characteristic_polynomial(a: ca.SX) -> tuple[list, list]:
    """(c, M): det(sI − A) coefficients c[0..n] (ascending, c[n] = 1) and M_1..M_n of the adjugate.

    Parameters
    ----------
    a : casadi.SX
        (n, n) state matrix A (symbolic).

    Returns
    -------
    tuple of list
        (c, M): the n+1 SX coefficients of det(sI − A) in ascending powers, and the n SX matrices
        M_1..M_n with adj(sI − A) = Σ M_k s^(n−k) (Faddeev–LeVerrier).
    """
    n = a.shape[0]
    eye = ca.SX.eye(n)
    c = [ca.SX(0)] * (n + 1)
    c[n] = ca.SX(1)
    m = eye
    mats = []
    for k in range(1, n + 1):
        mats.append(m)
        am = ca.mtimes(a, m)
        c[n - k] = -ca.trace(am) / k
        m = am + c[n - k] * eye
    return c, mats


def transfer_polynomials(a, b, c, d) -> tuple[Poly, Poly]:
    """(num, den) of C (sI − A)⁻¹ B + D in descending powers of s (SISO: b column, c row).

    Parameters
    ----------
    a : casadi.SX
        (n, n) state matrix A.
    b : casadi.SX
        (n, 1) input column B.
    c : casadi.SX
        (1, n) output row C.
    d : casadi.SX
        Scalar feedthrough D.

    Returns
    -------
    tuple of list
        (num, den): n+1 SX coefficients each, descending powers of s; den is det(sI − A), num is
        C adj(sI − A) B + D det(sI − A).
    """
    coef, mats = characteristic_polynomial(a)
    n = a.shape[0]
    den = [coef[n - j] for j in range(n + 1)]
    num = [d * coef[n]] + [ca.mtimes(ca.mtimes(c, mats[j - 1]), b) + d * coef[n - j] for j in range(1, n + 1)]
    return [ca.SX(x) for x in num], [ca.SX(x) for x in den]


def _pick(name: str | None, names: list[str], what: str, field: str) -> int:
    if name is None:
        if len(names) != 1:
            raise DataError(f"the model has {len(names)} {what}s {names}; name the one the data "
                            f"{'respond to' if what == 'input' else 'measure'} ({field}: \"...\")", field)
        return 0
    if name not in names:
        raise DataError(f"'{name}' is not a model {what} ({what}s: {names})", field)
    return names.index(name)


def _point(given: dict[str, float], names: list[str], field: str, what: str) -> np.ndarray:
    unknown = sorted(set(given) - set(names))
    if unknown:
        raise DataError(f"'{unknown[0]}' is not a model {what} ({what}s: {names})", f"{field}.{unknown[0]}")
    missing = [n for n in names if n not in given]
    if missing:
        hint = "the equilibrium, or with equilibrium 'solve' the start of the search" if what == "state" else "u0"
        raise DataError(f"no value for {what} '{missing[0]}'; give every {what} ({hint})", f"{field}.{missing[0]}")
    values = np.array([given[n] for n in names], dtype=float)
    if not np.all(np.isfinite(values)):
        raise DataError("values must be finite numbers", field)
    return values


def _check_supported(model: LinearisedOdeModel) -> None:
    if model.discrete is not None:
        raise ModelDefinitionError("the frequency response of a discrete-time model is not implemented; "
                                   "give the continuous-time equations", "model.discrete")
    for i, p in enumerate(model.parameters):
        if p.time_varying is not None:
            raise ModelDefinitionError("a linearisation needs constant parameters",
                                       f"model.parameters[{i}].time_varying")
    if not model.inputs:
        raise ModelDefinitionError("a frequency response needs an input; declare it in model.inputs",
                                   "model.inputs")
    if len(model.states) > MAX_LINEARISED_STATES:
        raise ModelDefinitionError(f"{len(model.states)} states; linearised frequency fits take at most "
                                   f"{MAX_LINEARISED_STATES}", "model.states")


class CompiledLinearisedModel(CompiledTransferFunction):
    """A linearised ODE model behaving as a `CompiledTransferFunction` (see the module docstring)."""

    model: LinearisedOdeModel

    def __init__(self, model: LinearisedOdeModel):
        _check_supported(model)
        self.model = model
        self.parameters = [p.name for p in model.parameters]
        op = model.operating_point
        self.input_index = _pick(model.input, list(model.inputs), "input", "model.input")
        self.output_names = list(model.measured_outputs())
        self.output_index = _pick(model.output, self.output_names, "output", "model.output")
        self.u0 = _point(op.inputs, list(model.inputs), "model.operating_point.inputs", "input")
        self.x0 = _point(op.states, list(model.states), "model.operating_point.states", "state")
        self.solve = op.equilibrium == "solve"
        self._plants: dict[tuple, tuple[Poly, Poly]] = {}
        base = self._compiled({})
        nx, npar = base.nx, base.np
        p = ca.SX.sym("p", npar)
        self.xe = ca.SX.sym("xe", nx) if self.solve else None
        self.p = ca.vertcat(p, self.xe) if self.solve else p
        self.equilibrium = self._equilibrium_function(base) if self.solve else None
        self.probe_points = self._probes(model)
        self._constraints(base, p)
        self.check_plant()

    # -- what CompiledTransferFunction asks -------------------------------------------------------
    def arguments(self, p):
        """``[p; x*(p)]`` with equilibrium "solve" (x* from the Newton rootfinder), else `p`."""
        return ca.vertcat(p, self.equilibrium(p)) if self.solve else p

    def coefficient_function(self, name: str, poly: Poly) -> ca.Function:
        """p (physical parameters) -> coefficient column, through x*(p) with equilibrium "solve" (`poly`
        in SX coefficients of ``self.p``: the parameters, and x* when solved for)."""
        inner = ca.Function(name + "_of_point", [self.p], [ca.vertcat(*poly)])
        if not self.solve:
            return inner
        p = ca.MX.sym("p", len(self.parameters))
        return ca.Function(name, [p], [inner(self.arguments(p))])

    def plant(self, constants: dict[str, float]) -> tuple[Poly, Poly]:
        """Numerator and denominator of the linearised plant with these constant values (cached); with
        equilibrium "solve", constants that change the model's equations are a `ModelDefinitionError`
        (`model.operating_point.equilibrium`): each data set would have its own equilibrium."""
        key = tuple(sorted(constants.items()))
        if key not in self._plants:
            cm = self._compiled(constants)
            if self.solve and constants and self._changes_equations(cm):
                raise ModelDefinitionError(
                    f"data-set constants {sorted(constants)} change the model's equations, so each data set "
                    "would have its own equilibrium; use equilibrium 'given' or keep them to the controller",
                    "model.operating_point.equilibrium")
            self._plants[key] = self._linearise(cm)
        return self._plants[key]

    def _changes_equations(self, cm: CompiledModel) -> bool:
        base = self._compiled({})
        rng = np.random.default_rng(0)
        x, u, p = rng.normal(size=cm.nx), rng.normal(size=cm.nu), rng.uniform(0.5, 1.5, size=cm.np)
        return not np.allclose(np.array(base.rhs(x, u, p, 0)), np.array(cm.rhs(x, u, p, 0)), equal_nan=True)

    def check_plant(self) -> None:
        """Check that the chosen output responds to the chosen input at the operating point (C adj(sI − A)
        B + D not identically zero; else a `ModelDefinitionError` on `model.output`)."""
        num, _ = self.plant({})
        if not self._strip_leading(num):
            raise ModelDefinitionError(
                f"output '{self.output_names[self.output_index]}' does not respond to input "
                f"'{self.model.inputs[self.input_index]}' at this operating point (C adj(sI−A) B + D ≡ 0)",
                "model.output")

    def operating_point(self, p: np.ndarray) -> dict[str, float]:
        """States and inputs of the operating point at the physical parameters p.

        Parameters
        ----------
        p : numpy.ndarray
            Physical parameters (declaration order).

        Returns
        -------
        dict of str to float
            State and input name to value: x*(p) with equilibrium "solve" (NaN where Newton fails),
            else the given states; the given inputs u0.
        """
        x = self._equilibrium_at(p) if self.solve else self.x0
        point = dict(zip(self.model.states, map(float, x)))
        point.update(zip(self.model.inputs, map(float, self.u0)))
        return point

    # -- construction -----------------------------------------------------------------------------
    def _compiled(self, constants: dict[str, float]) -> CompiledModel:
        model = self.model
        if constants:
            model = model.model_copy(update={"constants": {**model.constants, **constants}})
        cm = compile_model(model)
        x, u, p, t = (ca.SX.sym(n, k) for n, k in (("x", cm.nx), ("u", cm.nu), ("p", cm.np), ("t", 1)))
        if ca.depends_on(ca.vertcat(cm.rhs(x, u, p, t), cm.output(x, u, p, t)), t):
            raise ModelDefinitionError("the model depends on t; a linearisation needs a time-invariant "
                                       "model (give time-dependent forcing as an input)", "model.equations")
        return cm

    def _linearise(self, cm: CompiledModel) -> tuple[Poly, Poly]:
        x, u = ca.SX.sym("x", cm.nx), ca.SX.sym("u", cm.nu)
        p = self.p[:cm.np]
        f, h = cm.rhs(x, u, p, 0), cm.output(x, u, p, 0)[self.output_index]
        at = ca.vertcat(self.xe if self.solve else ca.DM(self.x0), ca.DM(self.u0))
        uk = u[self.input_index]
        a, b, c, d = (ca.substitute(ca.jacobian(expr, var), ca.vertcat(x, u), at)
                      for expr, var in ((f, x), (f, uk), (h, x), (h, uk)))
        return transfer_polynomials(a, b, c, d)

    def _equilibrium_function(self, cm: CompiledModel) -> ca.Function:
        """p -> x*(p); NaN where Newton fails (no exception: Ipopt then cuts its step back)."""
        x, p = ca.SX.sym("x", cm.nx), ca.SX.sym("p", cm.np)
        residual = ca.Function("f_at_u0", [x, p], [cm.rhs(x, ca.DM(self.u0), p, 0)])
        finder = ca.rootfinder("equilibrium_newton", "newton", residual,
                               {"abstol": 1e-12, "max_iter": 100, "error_on_fail": False,
                                "show_eval_warnings": False})
        scale = max(1.0, float(np.max(np.abs(np.r_[self.x0, self.u0]))))
        pm = ca.MX.sym("p", cm.np)
        xs = finder(ca.DM(self.x0), pm)
        # Newton may stop "converged" on NaN (sqrt of a negative level): a sum of squares keeps the NaN
        converged = ca.sumsqr(residual(xs, pm)) <= (EQUILIBRIUM_TOLERANCE * scale) ** 2
        fn = ca.Function("equilibrium", [pm], [xs + ca.if_else(converged, 0, np.nan)])
        if not np.all(np.isfinite(np.array(fn([q.value for q in self.model.parameters])))):
            raise DataError(
                f"no equilibrium f(x, u0, θ) = 0 found by Newton from the states given, with the parameters' "
                f"initial values and inputs {dict(zip(self.model.inputs, self.u0.tolist()))}; give a closer "
                "start in operating_point.states, check u0 (some inputs have no equilibrium), or use "
                "equilibrium 'given'", "model.operating_point")
        return fn

    def _equilibrium_at(self, p: np.ndarray) -> np.ndarray:
        if self.equilibrium is None:   # only equilibrium "solve" has x*(θ); "given" keeps x0
            raise ValueError("the operating point is given (equilibrium 'given'); there is no x*(θ) to solve for")
        return np.array(self.equilibrium(p), dtype=float).ravel()

    def _probes(self, model: LinearisedOdeModel) -> np.ndarray:
        """Generic parameter vectors (and their equilibria) telling structural zeros from accidents."""
        base = _probe_points(model)
        if not self.solve:
            return base
        rows = []
        for pt in base:
            xe = self._equilibrium_at(pt)
            rows.append(np.r_[pt, xe if np.all(np.isfinite(xe)) else self.x0])
        return np.array(rows)

    def _constraints(self, cm: CompiledModel, p: ca.SX) -> None:
        g, equality = [], []
        if cm.constraint is not None:
            g.append(cm.constraint(p))
            equality += list(cm.constraint_equality)
        if not self.solve:
            f = cm.rhs(ca.DM(self.x0), ca.DM(self.u0), p, 0)
            scale = max(1.0, float(np.max(np.abs(np.r_[self.x0, self.u0]))))
            for i, s in enumerate(cm.states):
                if ca.depends_on(f[i], p):
                    g.append(f[i])
                    equality.append(True)
                    continue
                value = float(ca.evalf(f[i]))
                if abs(value) > EQUILIBRIUM_TOLERANCE * scale:
                    raise DataError(
                        f"not an equilibrium whatever the parameters: d{s}/dt = {value:g} at this point; "
                        "give the states of a steady state, or use equilibrium 'solve'",
                        "model.operating_point.states")
        self.notes = []
        if not self.solve and len(equality) > len(cm.constraint_equality):
            self.notes.append("the equilibrium conditions f(x0, u0, θ) = 0 are equality constraints that the "
                              "covariance does not use: the standard errors are conservative")
        if g:
            self.constraint = ca.vertcat(*g)
            self.constraint_equality = np.array(equality, dtype=bool)
        else:
            self.constraint = None
            self.constraint_equality = np.zeros(0, dtype=bool)


def compile_linearised_model(model: LinearisedOdeModel) -> CompiledLinearisedModel:
    """Check the operating point and build the linearised transfer function; errors name the field.

    Parameters
    ----------
    model : LinearisedOdeModel
        A continuous-time ODE model with its operating point, input and output.

    Returns
    -------
    CompiledLinearisedModel
        The linearisation as a `CompiledTransferFunction`, its constraints including f(x0, u0, θ) = 0
        with equilibrium "given".

    Raises
    ------
    ModelDefinitionError
        When the model is discrete-time, has a time-varying parameter, no input, more than
        `MAX_LINEARISED_STATES` states, depends on t, or the output does not respond to the input.
    DataError
        When the input or output is not named where the model has several or is unknown, the operating
        point is incomplete, unknown or not finite, no equilibrium is found ("solve"), or the point is
        no equilibrium whatever the parameters ("given").
    """
    return CompiledLinearisedModel(model)
