"""Unmodelled first-order dynamics: a sensor (or anti-alias) lag on an output, an actuator filter on
an input, and an extra pole between two states — a missing first-order state in series.

Each adds a state w with τ·dw/dt = s − w, where s is what the lag acts on (the output h, the input
u, a state x_j as another equation sees it), and puts w where s was. At τ = 0 the lag is the
identity, so its first-order effect is the derivative of the lagged signal: w = s − τ·ds/dt + O(τ²).
The candidate's column is therefore −ds/dt per unit τ (an output column for the sensor, a forcing
∂f/∂s·(−ds/dt) for the others), and its coefficient in the screen is τ itself: a positive one is
physical, and it is the refit's start for a sensor lag (the warm start's Gauss-Newton step).

The lags are `generic`, like the input delay: at small τ a lag, a delay and any fast unmodelled
dynamics have the same first-order column, so they compete with each other by refit, and stand
behind a named law that explains as much.

A held input's derivative is a train of kicks at its switches: −τ·Δu_k at t_k, the same state
change as a forcing −Δu_k/Δt held over the interval that follows. A held input also makes ds/dt
jump at the samples, and a lag at time t_k averages what came before: the left-hand limit, where
the input had its previous value, is the one a sample sees.
"""
from __future__ import annotations

from typing import Any

import casadi as ca
import numpy as np

from greyfit.schemas.model import Model
from greyfit.solvers.data.preprocess import looks_piecewise_constant
from greyfit.solvers.model.compiler import CompiledModel
from greyfit.solvers.model.expressions import names_in, parse, substitute, unparse
from greyfit.solvers.screening.augment import fresh_name, replace_in_equations, rewrite_output, with_parameter
from greyfit.solvers.screening.candidate import Candidate, LibraryContext, Regressor
from greyfit.solvers.screening.families.base import NeedsTracedEquation, Scope, bind, sensitivity_regressor
from greyfit.solvers.screening.families.inputs import NeedsInputs

LOWEST_TAU = 0.1   # the new time constant's lower bound, in sample intervals: the refit's RK4 stays stable


def add_lag(model: Model, stem: str, source: str, dt: float) -> tuple[Model, str, str]:
    """`model` with a new state w, τ·dw/dt = source − w, and a new parameter τ (start one sample).

    Parameters
    ----------
    model : Model
        The model (not changed: a copy is returned).
    stem : str
        Stem of the new state's name (the parameter is ``<stem>_tau``).
    source : str
        The lagged signal (model syntax).
    dt : float
        The sample interval: τ starts at dt, bounded below by `LOWEST_TAU`·dt.

    Returns
    -------
    tuple of (Model, str, str)
        The augmented model, the new state's name and the new parameter's name.
    """
    w = fresh_name(model, stem)
    tau = fresh_name(model.model_copy(update={"states": [*model.states, w]}), f"{stem}_tau")
    model = with_parameter(model, tau, float(dt), lower=LOWEST_TAU * float(dt))
    equations = {**model.equations, w: f"(({source}) - {w}) / {tau}"}
    outputs = model.measured_outputs()   # written out: the new state is not measured
    return model.model_copy(update={"states": [*model.states, w], "equations": equations,
                                    "outputs": outputs}), w, tau


def _rates(cm: CompiledModel) -> ca.Function:
    """(x, u, p, t) -> (dx/dt, dh/dt) with dh/dt = ∂h/∂x·f + ∂h/∂t (an input's own change left out)."""
    x, u, p, t = ca.SX.sym("x", cm.nx), ca.SX.sym("u", cm.nu), ca.SX.sym("p", cm.np), ca.SX.sym("t")
    f, h = cm.rhs(x, u, p, t), cm.output(x, u, p, t)
    hdot = ca.mtimes(ca.jacobian(h, x), f) + ca.jacobian(h, t)
    return ca.Function("greyfit_rates", [x, u, p, t], [f, hdot])


def left_rates(ctx: LibraryContext) -> list[tuple[np.ndarray, np.ndarray]]:
    """(dx/dt (nx, n), dh/dt (ny, n)) along the trace, per experiment: with held inputs, their
    left-hand limits at the samples (the previous input value), which a lag sees.

    Parameters
    ----------
    ctx : LibraryContext
        The model and the fitted trajectory.

    Returns
    -------
    list of tuple of numpy.ndarray
        Per experiment, the state and output rates at each sample.
    """
    cm = ctx.trace.cm
    fn = cm.derive(("lag_rates",), lambda: _rates(cm))
    out = []
    for x, u, p, t in zip(ctx.trace.x, ctx.trace.u, ctx.trace.p, ctx.trace.t):
        n = t.size
        seen = u.copy()
        if u.size and all(looks_piecewise_constant(row) for row in u):
            seen[:, 1:] = u[:, :-1]
        f, hdot = fn.map(n)(x, seen, np.repeat(np.asarray(p, dtype=float).reshape(-1, 1), n, 1), t[None, :])
        out.append((np.array(f), np.array(hdot)))
    return out


def input_rate(u: np.ndarray, t: np.ndarray) -> np.ndarray:
    """du/dt as a forcing held or interpolated like the input: a held input's switch Δu_k at t_k
    as Δu_k/Δt over the interval after it, a smooth input's derivative at the samples.

    Parameters
    ----------
    u : numpy.ndarray
        The input's samples, (n,).
    t : numpy.ndarray
        Their times, (n,).

    Returns
    -------
    numpy.ndarray
        (n,) the rate.
    """
    if u.size < 3:
        return np.zeros_like(u)
    if looks_piecewise_constant(u):
        rate = np.zeros_like(u)
        rate[1:] = np.diff(u) / np.diff(t)
        return rate
    return np.gradient(u, t)


def inlined_equation(model: Model, eq: str):
    """The AST of state `eq`'s equation with every definition it uses inlined (recursively).

    Parameters
    ----------
    model : Model
        The model.
    eq : str
        The state whose equation is read.

    Returns
    -------
    tuple
        The equation's AST, naming states, inputs, parameters, constants and t only.
    """
    node = parse(model.equations[eq], f"equations.{eq}")
    defs = {k: parse(v, f"definitions.{k}") for k, v in model.definitions.items()}
    for _ in range(len(defs) + 1):   # definitions refer to earlier ones only: this many passes suffice
        used = names_in(node) & defs.keys()
        if not used:
            break
        for name in used:
            node = substitute(node, name, defs[name])
    return node


def _dt(ctx: LibraryContext) -> float:
    return float(np.median(np.concatenate([np.diff(t) for t in ctx.trace.t])))


class SensorLag:
    """The sensor (or its anti-alias filter) of an output answers with a first-order lag."""

    name = "sensor_lag"
    scope: Scope = "output"
    generic = True

    def supports(self, ctx: LibraryContext) -> bool:
        """Whether the output path is screened (the fitted outputs are known).

        Parameters
        ----------
        ctx : LibraryContext
            The model, the fitted trajectory and the discovery options.

        Returns
        -------
        bool
            True when `ctx.outputs` is given.
        """
        return ctx.outputs is not None

    def rewrite(self, model: Model, **spec: Any) -> tuple[Model, list[str]]:
        """Output h becomes a new state w, τ·dw/dt = h − w.

        Parameters
        ----------
        model : Model
            The model to rewrite (not changed: a copy is returned).
        **spec : Any
            `output`: the measured output's name; `dt`: the sample interval.

        Returns
        -------
        tuple of (Model, list of str)
            The rewritten model and the new parameter τ's name.
        """
        h = model.measured_outputs()[spec["output"]]
        model, w, tau = add_lag(model, f"{spec['output']}_sensed", h, spec["dt"])
        return rewrite_output(model, spec["output"], w), [tau]

    def candidates(self, ctx: LibraryContext) -> list[Candidate]:
        """One lag per measured output, its column −dh/dt.

        Parameters
        ----------
        ctx : LibraryContext
            The model, the fitted trajectory and the fitted outputs.

        Returns
        -------
        list of Candidate
            One candidate per output.
        """
        assert ctx.outputs is not None   # supports() said so
        rates = left_rates(ctx)
        dt = _dt(ctx)
        return [Candidate(self.name, {}, f"{name} = w, {name}_sensed_tau*dw/dt = h - w",
                          f"the sensor of {name} lags by a first-order time constant",
                          bind(self, output=name, dt=dt), outputs={j: [-hdot[j] for _, hdot in rates]},
                          sign=1.0, family=f"sensor_lag:{name}", generic=self.generic)
                for j, name in enumerate(ctx.outputs.names)]


class InputLag(NeedsInputs):
    """An actuator (or input filter) passes its input on through a first-order lag."""

    name = "input_lag"
    scope: Scope = "input"
    generic = True

    def rewrite(self, model: Model, **spec: Any) -> tuple[Model, list[str]]:
        """Input u becomes, in the state equations and definitions, a new state w with τ·dw/dt = u − w.

        Parameters
        ----------
        model : Model
            The model to rewrite (not changed: a copy is returned).
        **spec : Any
            `input`: the input's name; `dt`: the sample interval.

        Returns
        -------
        tuple of (Model, list of str)
            The rewritten model and the new parameter τ's name.
        """
        u = spec["input"]
        w = fresh_name(model, f"{u}_acting")
        # the equations read w before it is declared: add_lag then declares it under that same name
        lagged, _, tau = add_lag(replace_in_equations(model, u, w), w, u, spec["dt"])
        return lagged, [tau]

    def candidates(self, ctx: LibraryContext) -> list[Candidate]:
        """One lag per input, its column ∂f/∂u·(−du/dt) (`input_rate`).

        Parameters
        ----------
        ctx : LibraryContext
            The model and the fitted trajectory.

        Returns
        -------
        list of Candidate
            One candidate per input that some traced equation feels.
        """
        out = []
        dt = _dt(ctx)
        for k, u in enumerate(ctx.trace.cm.inputs):
            change = [-input_rate(x, t) for x, t in zip(ctx.input_values(u), ctx.trace.t)]
            reg = sensitivity_regressor(ctx.trace, ctx.trace.ju, k, change)
            if reg:
                out.append(Candidate(self.name, reg, f"{u} -> w, {u}_acting_tau*dw/dt = {u} - w",
                                     f"input {u} acts through a first-order lag (an actuator or input filter)",
                                     bind(self, input=u, dt=dt), sign=1.0, family=f"input_lag:{u}",
                                     generic=self.generic, variables=(u,)))
        return out


class ExtraPole(NeedsTracedEquation):
    """State x_j reaches the equation of x_i through a first-order lag: a state the model lacks, in
    series (a wall between a heater and a node, a compliant shaft, a mixing volume)."""

    name = "extra_pole"
    scope: Scope = "equation"
    generic = True

    def rewrite(self, model: Model, **spec: Any) -> tuple[Model, list[str]]:
        """In d(equation)/dt, state `source` becomes a new state w with τ·dw/dt = source − w.

        Parameters
        ----------
        model : Model
            The model to rewrite (not changed: a copy is returned).
        **spec : Any
            `equation`: the state whose equation sees the lag; `source`: the lagged state; `dt`: the
            sample interval.

        Returns
        -------
        tuple of (Model, list of str)
            The rewritten model and the new parameter τ's name.
        """
        eq, src = spec["equation"], spec["source"]
        model, w, tau = add_lag(model, f"{src}_to_{eq}", src, spec["dt"])
        node = substitute(inlined_equation(model, eq), src, parse(w, "lag"))
        return model.model_copy(update={"equations": {**model.equations, eq: unparse(node)}}), [tau]

    def candidates(self, ctx: LibraryContext) -> list[Candidate]:
        """A lag of every other state named in a traced equation's text, its column ∂f_i/∂x_j·(−dx_j/dt);
        not in a kinematic identity dx/dt = v (a position is the integral of its velocity, unlagged).

        A state the equation reaches through a definition is lagged alike: the rewrite substitutes in
        the equation with its definitions inlined (a definition other equations share stays as it
        is for them), so every spelling of the model, with or without intermediate definitions,
        offers the same lags with the same columns.

        Parameters
        ----------
        ctx : LibraryContext
            The model and the fitted trajectory.

        Returns
        -------
        list of Candidate
            One candidate per (equation, state) pair.
        """
        rates = left_rates(ctx)
        dt = _dt(ctx)
        out = []
        for eq in ctx.force_equations():   # a kinematic identity dx/dt = v has no lag
            i = ctx.states.index(eq)
            named = names_in(inlined_equation(ctx.model, eq))
            for j, src in enumerate(ctx.states):
                if j == i or src not in named:
                    continue
                cols = [jx[:, i, j] * -f[j] for jx, (f, _) in zip(ctx.trace.jx, rates)]
                if not any(np.any(c != 0) for c in cols):
                    continue
                reg: Regressor = {i: cols}
                out.append(Candidate(self.name, reg, f"{src} -> w in d{eq}/dt, tau*dw/dt = {src} - w",
                                     f"{src} acts on {eq} through a first-order lag (a missing state in series)",
                                     bind(self, equation=eq, source=src, dt=dt), sign=1.0,
                                     family=f"extra_pole:{eq}:{src}", variables=(src,), generic=self.generic))
        return out


__all__ = ["SensorLag", "InputLag", "ExtraPole", "add_lag", "left_rates", "input_rate", "inlined_equation"]
