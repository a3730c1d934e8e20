"""Compile a transfer-function model into CasADi coefficient vectors of each closed loop.

Coefficients are in descending powers of s and are SX expressions of the full physical parameter
vector ``p`` (declaration order), so the fit can differentiate through them.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from greyfit.schemas.frequency import LinearisedOdeModel, TransferFunctionModel
from greyfit.solvers.errors import ModelDefinitionError
from greyfit.solvers.model.constraints import compile_constraints
from greyfit.solvers.model.expressions import compile_expression
from greyfit.solvers.model.parameters import DeclaresParameters

Poly = list  # list of SX scalars, descending powers of s


@dataclass
class ClosedLoop:
    """num(s)/den(s) of one measured (or stability-only) loop, common factors s^k cancelled."""

    name: str
    num: Poly
    den: Poly
    num_fn: ca.Function   # p -> num coefficients (column)
    den_fn: ca.Function   # p -> den coefficients
    cancelled: int = 0    # powers of s removed from both


@dataclass
class CompiledTransferFunction:
    model: TransferFunctionModel | LinearisedOdeModel   # the latter in solvers.frequency.linearise
    parameters: list[str]
    p: ca.SX                               # what the coefficients are expressions of
    constraint: ca.SX | None          # g(p) >= 0 (== 0 where equality)
    constraint_equality: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    probe_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))

    def arguments(self, p):
        """What the coefficient expressions take (``self.p``) from the physical parameter vector.

        Parameters
        ----------
        p : casadi.SX or casadi.MX or numpy.ndarray
            The full physical parameter vector (declaration order).

        Returns
        -------
        casadi.SX or casadi.MX or numpy.ndarray
            `p` itself: a transfer function's coefficients are expressions of the parameters directly.
        """
        return p

    def plant(self, constants: dict[str, float]) -> tuple[Poly, Poly]:
        """Numerator and denominator of P(s) with these constant values.

        Parameters
        ----------
        constants : dict of str to float
            Values that override the model's constants (e.g. one data set's).

        Returns
        -------
        tuple of list
            (numerator, denominator): SX coefficients of ``self.p``, descending powers of s.

        Raises
        ------
        ModelDefinitionError
            When a coefficient expression does not compile (the field names the coefficient).
        """
        env = self._env(constants)
        model = self._declared()
        return (_coefficients(model.numerator, env, "model.numerator"),
                _coefficients(model.denominator, env, "model.denominator"))

    def coefficient_function(self, name: str, poly: Poly) -> ca.Function:
        """p (physical parameters) -> coefficient column.

        Parameters
        ----------
        name : str
            Name of the CasADi Function.
        poly : list
            SX coefficients of ``self.p``.

        Returns
        -------
        casadi.Function
            ``self.p`` -> the coefficients as one column.
        """
        return ca.Function(name, [self.p], [ca.vertcat(*poly)])

    def loop(self, name: str, constants: dict[str, float]) -> ClosedLoop:
        """The response measured with these constant values (e.g. this data set's Kp, Ki).

        With `model.feedback`, the closed loop PC/(1+PC) or P/(1+PC) by what it says is measured;
        else the plant. Common factors s^k of numerator and denominator are cancelled.

        Parameters
        ----------
        name : str
            Name of the loop (the data set's), used in messages.
        constants : dict of str to float
            Values that override the model's constants.

        Returns
        -------
        ClosedLoop
            The loop's numerator and denominator, their coefficient Functions and the cancelled power.

        Raises
        ------
        ModelDefinitionError
            When a coefficient does not compile, the controller is improper, or the closed-loop
            denominator is identically zero.
        """
        env = self._env(constants)
        m = self.model
        num, den = self.plant(constants)
        if m.feedback is not None:
            c_num = _coefficients(m.feedback.controller.num, env, "model.feedback.controller.num")
            c_den = _coefficients(m.feedback.controller.den, env, "model.feedback.controller.den")
            self._check_proper(c_num, c_den, "model.feedback.controller")
            char = poly_add(poly_mul(den, c_den), poly_mul(num, c_num))
            num = poly_mul(num, c_num) if m.feedback.measured == "PC/(1+PC)" else poly_mul(num, c_den)
            den = char
        num, den, cancelled = self._cancel_common_s(num, den)
        if not den:
            raise ModelDefinitionError(f"the closed-loop denominator of '{name}' is identically zero",
                                       "model.denominator")
        return ClosedLoop(name, num, den, self.coefficient_function("num", num),
                          self.coefficient_function("den", den), cancelled)

    def check_plant(self) -> None:
        """Check that the plant's coefficients compile and that it is proper.

        Raises
        ------
        ModelDefinitionError
            When a coefficient does not compile, the denominator is identically zero, or the numerator's
            degree exceeds the denominator's (field `model.numerator` / `model.denominator`).
        """
        env = self._env({})
        model = self._declared()
        num = _coefficients(model.numerator, env, "model.numerator")
        den = _coefficients(model.denominator, env, "model.denominator")
        self._check_proper(num, den, "model")

    # -- helpers ---------------------------------------------------------------------------------
    def _declared(self) -> TransferFunctionModel:
        """The declared numerator/denominator; a class built from another model overrides their users."""
        if not isinstance(self.model, TransferFunctionModel):
            raise TypeError(f"{type(self).__name__} holds a {type(self.model).__name__}, which has no "
                            "numerator/denominator: it must override plant() and check_plant()")
        return self.model

    def _env(self, constants: dict[str, float]) -> dict[str, object]:
        env: dict[str, object] = {n: self.p[i] for i, n in enumerate(self.parameters)}
        env.update(self.model.constants)
        env.update(constants)
        return env

    def is_zero(self, expr) -> bool:
        """Zero for every probe parameter vector: a structural zero (e.g. Ki*b2 with Ki = 0).

        Parameters
        ----------
        expr : casadi.SX
            An expression of ``self.p``.

        Returns
        -------
        bool
            True when it evaluates to exactly 0 at every one of `probe_points`.
        """
        fn = ca.Function("c", [self.p], [expr])
        return all(float(fn(pt)) == 0.0 for pt in self.probe_points)

    def _strip_leading(self, poly: Poly) -> Poly:
        k = 0
        while k < len(poly) and self.is_zero(poly[k]):
            k += 1
        return poly[k:]

    def _check_proper(self, num: Poly, den: Poly, where: str) -> None:
        n, d = self._strip_leading(num), self._strip_leading(den)
        field_num = "numerator" if where == "model" else "num"
        field_den = "denominator" if where == "model" else "den"
        if not d:
            raise ModelDefinitionError("the denominator is identically zero", f"{where}.{field_den}")
        if len(n) > len(d):
            raise ModelDefinitionError(
                f"improper transfer function: numerator degree {len(n) - 1} exceeds denominator degree "
                f"{len(d) - 1}; a physical system has at most as many zeros as poles",
                f"{where}.{field_num}")

    def _cancel_common_s(self, num: Poly, den: Poly) -> tuple[Poly, Poly, int]:
        num, den = self._strip_leading(num), self._strip_leading(den)
        k = 0
        while len(num) > 1 and len(den) > 1 and self.is_zero(num[-1]) and self.is_zero(den[-1]):
            num, den, k = num[:-1], den[:-1], k + 1
        return num, den, k


def poly_mul(a: Poly, b: Poly) -> Poly:
    """Product of two polynomials.

    Parameters
    ----------
    a, b : list
        Coefficients (SX scalars), descending powers of s.

    Returns
    -------
    list
        The len(a) + len(b) − 1 coefficients of a·b.
    """
    out = [ca.SX(0)] * (len(a) + len(b) - 1)
    for i, x in enumerate(a):
        for j, y in enumerate(b):
            out[i + j] = out[i + j] + x * y
    return out


def poly_add(a: Poly, b: Poly) -> Poly:
    """Sum of two polynomials, the shorter padded with leading zeros.

    Parameters
    ----------
    a, b : list
        Coefficients (SX scalars), descending powers of s.

    Returns
    -------
    list
        The max(len(a), len(b)) coefficients of a + b.
    """
    n = max(len(a), len(b))
    a = [ca.SX(0)] * (n - len(a)) + list(a)
    b = [ca.SX(0)] * (n - len(b)) + list(b)
    return [x + y for x, y in zip(a, b)]


def _coefficients(texts: list[str], env: dict, where: str) -> Poly:
    return [ca.SX(compile_expression(t, env, f"{where}[{i}]")) for i, t in enumerate(texts)]


def _probe_points(model: DeclaresParameters, n: int = 3, seed: int = 12345) -> np.ndarray:
    """Generic parameter vectors (around the guesses) to tell structural zeros from accidental ones."""
    rng = np.random.default_rng(seed)
    base = np.array([p.value if p.value != 0 else 1.0 for p in model.parameters])
    return base[None, :] * rng.uniform(0.5, 1.5, size=(n, base.size)) + rng.uniform(0.01, 0.1, (n, base.size))


def compile_transfer_function(model: TransferFunctionModel) -> CompiledTransferFunction:
    """Compile constraints and check the plant; loops are built per data set with `loop`.

    Parameters
    ----------
    model : TransferFunctionModel
        The declared transfer-function model.

    Returns
    -------
    CompiledTransferFunction
        Its parameters as one SX vector, the compiled constraints g(p) (or None) and probe points for
        telling structural zeros apart.

    Raises
    ------
    ModelDefinitionError
        When a coefficient or constraint does not compile, or the plant is improper or has a zero
        denominator; the field is named.
    """
    names = [p.name for p in model.parameters]
    p = ca.SX.sym("p", len(names))
    tf = CompiledTransferFunction(model, names, p, None, probe_points=_probe_points(model))
    tf.check_plant()
    if model.constraints:
        env = tf._env({})
        g, tf.constraint_equality = compile_constraints(model.constraints, env, set(env), "model.constraints")
        tf.constraint = ca.vertcat(*g)
    return tf
