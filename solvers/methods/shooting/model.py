"""The output-error model every shooting method shares: the compiled step, simulation, sensitivities.

Single shooting (`single.py`) and multiple shooting (`multiple.py`) build their problems from it; the
structured compiled form (`structured.py`) evaluates the same NLP from per-sample blocks, and the hybrid
solver (`hybrid.py`) solves multiple shooting with the gaps' curvature (`curvature.py`).
"""
from __future__ import annotations

import threading
import weakref
from collections import OrderedDict

import casadi as ca
import numpy as np

from greyfit.schemas.fit import FitOptions
from greyfit.solvers.data.experiments import ExperimentData, fill_missing
from greyfit.solvers.dynamics.columns import Columns
from greyfit.solvers.dynamics.compiled import compiled
from greyfit.solvers.dynamics.function_cache import FunctionCache
from greyfit.solvers.dynamics.integration import integrator_of, make_step
from greyfit.solvers.methods.shooting import structured as shooting_structured
from greyfit.solvers.methods.shooting.later_drops import LaterDrops
from greyfit.solvers.model.compiler import CompiledModel
from greyfit.solvers.model.parameters import ParameterLayout
from greyfit.solvers.nlp.problem import (
    output_weights,
    state_scales,
)

# "serial": measured faster than "thread" on 2 cores for per-sample intervals (thread start-up
# outweighs the tiny per-interval work), and it leaves the other core to a second worker.
MAP_MODE = "serial"

# The last simulations by step, record, x0 and parameters: a fit simulates its optimum for the
# residual channels, the lack-of-fit screen and its output scorer (three 0.25 ms simulations of the
# seat model). A prepared record is read-only and shared by the steps of one fit (`prepared_once`),
# so its identity is its content. Long trajectories are not kept (their size, not their time).
_STATES: "OrderedDict[tuple, tuple]" = OrderedDict()
_STATES_LOCK = threading.Lock()
STATES_KEPT_BYTES = 16 * 1024 * 1024


_STATES_DROPS = LaterDrops(_STATES, _STATES_LOCK)   # entries go with their records (finalizers)


class OutputErrorModel:
    """Shared pieces of both shooting methods: integrator, weights, masks, x0 handling."""

    def __init__(self, cm: CompiledModel, data: list[ExperimentData], layout: ParameterLayout,
                 options: FitOptions):
        self.cm, self.data, self.layout, self.options = cm, data, layout, options
        self.step = make_step(cm, options)
        self.weights = output_weights(cm, data, options)
        self.xscale = state_scales(cm, data)
        self.free_x0 = [[i for i in range(cm.nx) if i not in d.x0_known] for d in data]
        self.reused = isinstance(cm, CompiledModel)   # kept across requests (not a stand-in)
        self._maps = cm.derive(("maps",), FunctionCache) if self.reused else FunctionCache()
        self._simulated: "OrderedDict[bytes, tuple]" = OrderedDict()
        self._sensitivities: tuple[ca.Function, ca.Function] | None = None
        self.simulation_failures: list[str] = []   # why a numeric simulation failed, if one did
        self.node_notes: list[tuple[str, str]] = []   # (experiment, why) a start's simulation diverged
        self.structured_data: np.ndarray | None = None   # the structured NLP's data vector, built once
        self.single_pass_token: float | None = None   # this model's record in single shooting's callbacks

    def sensitivity_functions(self) -> tuple[ca.Function, ca.Function]:
        """(step -> x+, ∂x+/∂x, ∂x+/∂p) and (output -> y, ∂y/∂x, ∂y/∂p), built once (compiled C
        where the step is an SX expression and a compiler is present).

        Returns
        -------
        step_sens : casadi.Function
            (x, u0, u1, p, t0, dt) -> (x+, ∂x+/∂x, ∂x+/∂p).
        out_sens : casadi.Function
            (x, u, p, t) -> (y, ∂y/∂x, ∂y/∂p).
        """
        if self._sensitivities is None:
            o = self.options
            step_sens, out_sens = self.cm.derive(
                ("sensitivities", o.integrator, o.substeps, o.input_interpolation),
                lambda: _sensitivity_functions(self.cm, self.step, o))
            samples = sum(d.n for d in self.data)
            if step_sens.is_a("SXFunction"):   # CVODES cannot be generated as C
                step_sens, _ = compiled(step_sens, 2 * samples)
            out_sens, _ = compiled(out_sens, 2 * samples)
            self._sensitivities = (step_sens, out_sens)
        return self._sensitivities

    def output_jacobians(self, e: int, states: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """y, ∂y/∂x and ∂y/∂p of experiment e along `states`, as numbers (one compiled sample loop).

        The checks after every fit (the lack-of-fit screen, the covariance's Jacobian where the
        structured form does not apply) ask for these; a CasADi `map` built and unpacked per call
        cost more than the arithmetic.

        Parameters
        ----------
        e : int
            Index of the experiment.
        states : numpy.ndarray
            States at every sample, shape (nx, N).
        p : numpy.ndarray
            The experiment's full parameter vector, shape (np,).

        Returns
        -------
        y : numpy.ndarray
            Outputs, shape (ny, N).
        hx : numpy.ndarray
            ∂y/∂x per sample, shape (N, ny, nx).
        hp : numpy.ndarray
            ∂y/∂p per sample, shape (N, ny, np).
        """
        cm, o, n = self.cm, self.options, self.data[e].n
        key = ("sensitivities", o.integrator, o.substeps, o.input_interpolation)
        if self.reused:
            out = self.cm.derive(("output_jacobians",), lambda: Columns(
                ca.Function("greyfit_out_jac", *_dense_outputs(self.cm.derive(
                    key, lambda: _sensitivity_functions(cm, self.step, o))[1])), 4 * n))
        else:
            out = Columns(ca.Function("greyfit_out_jac", *_dense_outputs(
                _sensitivity_functions(cm, self.step, o)[1])), compile=False)
        d = self.data[e]
        y, hx, hp = out(np.asarray(states, dtype=float), d.u, np.asarray(p, dtype=float).ravel(), d.t[None, :], n=n)
        return (y, hx.reshape(cm.ny, n, cm.nx).transpose(1, 0, 2),
                hp.reshape(cm.ny, n, cm.np).transpose(1, 0, 2))

    def simulator(self, n: int) -> ca.Function:
        """The step accumulated over `n` intervals (cached per integrator settings and `n`).

        Parameters
        ----------
        n : int
            Number of intervals.

        Returns
        -------
        casadi.Function
            (x0, u0, u1, p, t0, dt), inputs stacked over the intervals -> states after each step (nx × n).
        """
        o = self.options
        return self._maps.get(("sim", o.integrator, o.substeps, o.input_interpolation, n),
                              lambda: self.step.mapaccum("sim", n))

    def output_map(self, n: int) -> ca.Function:
        """The output function mapped over `n` samples (cached).

        Parameters
        ----------
        n : int
            Number of samples.

        Returns
        -------
        casadi.Function
            (states, u, p, t), each stacked over the samples -> outputs (ny × n).
        """
        return self._maps.get(("out", n), lambda: self.cm.output.map(n))

    def numeric_functions(self) -> tuple[Columns, Columns]:
        """(step, output) evaluated on numpy columns: compiled C without copies where available.

        Returns
        -------
        step : Columns
            The integrator step on numpy columns.
        output : Columns
            The output function on numpy columns.
        """
        o = self.options
        samples = sum(d.n for d in self.data)
        return self._maps.get(("numeric", o.integrator, o.substeps, o.input_interpolation),
                              lambda: (Columns(self.step, 4 * samples, self.reused),
                                       Columns(self.cm.output, 4 * samples, self.reused)))

    def step_inputs(self, d: ExperimentData, i0: int, i1: int):
        """Numeric step inputs for intervals i0..i1-1: u0, u1, t0, dt (each horizontally stacked).

        Parameters
        ----------
        d : ExperimentData
            The experiment.
        i0, i1 : int
            First interval and one past the last.

        Returns
        -------
        u0, u1 : numpy.ndarray
            Inputs at the start and end of each interval, shape (nu, i1 − i0).
        t0, dt : numpy.ndarray
            Start time and length of each interval, shape (1, i1 − i0).
        """
        return d.u[:, i0:i1], d.u[:, i0 + 1:i1 + 1], d.t[i0:i1][None, :], np.diff(d.t[i0:i1 + 1])[None, :]

    def trajectory(self, e: int, x0, p):
        """States at every sample of experiment e from x0 (nx × N).

        Parameters
        ----------
        e : int
            Index of the experiment.
        x0 : casadi.MX or numpy.ndarray
            Initial state, shape (nx,).
        p : casadi.MX or numpy.ndarray
            The experiment's full parameter vector, shape (np,).

        Returns
        -------
        casadi.MX or casadi.DM
            States at every sample, the initial state first, shape (nx, N).
        """
        d = self.data[e]
        u0, u1, t0, dt = self.step_inputs(d, 0, d.n - 1)
        xs = self.simulator(d.n - 1)(x0, u0, u1, ca.repmat(p, 1, d.n - 1), t0, dt)
        return ca.horzcat(x0, xs)

    def numeric_states(self, e: int, x0: np.ndarray, p: np.ndarray) -> np.ndarray:
        """`trajectory` for numbers (nx × N); raises RuntimeError where the integrator fails.

        Parameters
        ----------
        e : int
            Index of the experiment.
        x0 : numpy.ndarray
            Initial state, shape (nx,).
        p : numpy.ndarray
            The experiment's full parameter vector, shape (np,).

        Returns
        -------
        numpy.ndarray
            States at every sample, shape (nx, N) (nx × 1 for a single sample).

        Raises
        ------
        RuntimeError
            When the integrator fails (`numeric_trajectory` turns this into NaN).
        """
        d = self.data[e]
        x0 = np.asarray(x0, dtype=float).reshape(-1, 1)
        if d.n < 2:
            return x0
        step = self.numeric_functions()[0]
        p = np.asarray(p, dtype=float)
        key = (id(step), id(d), x0.tobytes(), p.tobytes())
        with _STATES_LOCK:
            _STATES_DROPS.drain()
            known = _STATES.get(key)
        # the entry holds its step, and its record weakly (it is dropped with the record, so an id in a
        # key is never reused while it lives, and a fit's record does not outlive the fit here)
        if known is not None and known[0] is step and known[1]() is d:
            return known[2].copy()
        u0, u1, t0, dt = self.step_inputs(d, 0, d.n - 1)
        xs, = step(x0, u0, u1, p, t0, dt, n=d.n - 1, accumulate=True)
        states = np.hstack([x0, xs])
        if states.nbytes <= STATES_KEPT_BYTES:
            with _STATES_LOCK:
                _STATES_DROPS.drain()
                _STATES[key] = (step, weakref.ref(d), states)
                while len(_STATES) > 4:
                    _STATES.popitem(last=False)
            weakref.finalize(d, _STATES_DROPS.drop, key)
        return states.copy()

    def numeric_outputs(self, e: int, states: np.ndarray, p: np.ndarray) -> np.ndarray:
        """`outputs_of` for numbers (ny × N).

        Parameters
        ----------
        e : int
            Index of the experiment.
        states : numpy.ndarray
            States at every sample, shape (nx, N).
        p : numpy.ndarray
            The experiment's full parameter vector, shape (np,).

        Returns
        -------
        numpy.ndarray
            Outputs at every sample, shape (ny, N).
        """
        d = self.data[e]
        return self.numeric_functions()[1](states, d.u, np.asarray(p, dtype=float), d.t[None, :], n=d.n)[0]

    def numeric_trajectory(self, e: int, x0: np.ndarray, p: np.ndarray) -> np.ndarray:
        """`trajectory` for numbers; NaN (and the reason kept) when the integrator fails.

        CVODES raises when it cannot take a step (a stiff or diverging model); a fit that reaches
        such a point must end as a result that says so, not as an exception.

        Parameters
        ----------
        e : int
            Index of the experiment.
        x0 : numpy.ndarray
            Initial state, shape (nx,).
        p : numpy.ndarray
            The experiment's full parameter vector, shape (np,).

        Returns
        -------
        numpy.ndarray
            States at every sample, shape (nx, N); all NaN when the integrator failed, the reason
            appended to `simulation_failures`.
        """
        try:
            return self.numeric_states(e, x0, p)
        except RuntimeError as exc:
            self.simulation_failures.append(
                f"the simulation of experiment '{self.data[e].name}' failed ({_first_line(exc)})")
            return np.full((self.cm.nx, self.data[e].n), np.nan)

    def outputs_of(self, e: int, states, p):
        """Outputs of experiment e as a graph (symbolic states or θ); `numeric_outputs` for numbers.

        Parameters
        ----------
        e : int
            Index of the experiment.
        states : casadi.MX
            States at every sample, shape (nx, N).
        p : casadi.MX
            The experiment's full parameter vector, shape (np,).

        Returns
        -------
        casadi.MX
            Outputs at every sample, shape (ny, N).
        """
        d = self.data[e]
        return self.output_map(d.n)(states, d.u, ca.repmat(p, 1, d.n), d.t[None, :])

    def residual_of(self, e: int, y_model):
        """Weighted residual at the measured (non-null) samples, column-major order.

        Parameters
        ----------
        e : int
            Index of the experiment.
        y_model : casadi.MX
            Model outputs at every sample, shape (ny, N).

        Returns
        -------
        casadi.MX
            Output weight × (model − measured) at the measured samples, sample by sample.
        """
        d = self.data[e]
        mask = d.mask.ravel(order="F")
        wts = np.tile(self.weights, d.n)
        if mask.all():   # no gather node: large index lists are slow to differentiate in MX
            return wts * (ca.vec(y_model) - d.y.ravel(order="F"))
        idx = np.flatnonzero(mask)
        return wts[idx] * (ca.vec(y_model)[idx.tolist()] - d.y.ravel(order="F")[idx])

    def x0_guess(self, e: int) -> np.ndarray:
        """Known initial states, else the first measured sample of a directly measured state, else 0.

        Parameters
        ----------
        e : int
            Index of the experiment.

        Returns
        -------
        numpy.ndarray
            The guessed initial state, shape (nx,), physical units.
        """
        d, x0 = self.data[e], np.zeros(self.cm.nx)
        for out, state in self.cm.direct_outputs.items():
            x0[self.cm.states.index(state)] = fill_missing(d.y[self.cm.outputs.index(out)], d.t)[0]
        for i, v in d.x0_known.items():
            x0[i] = v
        return x0

    def assemble_x0(self, e: int, free_scaled):
        """Initial state vector from known values and the (scaled) free entries.

        Parameters
        ----------
        e : int
            Index of the experiment.
        free_scaled : casadi.MX
            The experiment's free initial states, scaled by `xscale`, in state order.

        Returns
        -------
        casadi.MX
            The full initial state, shape (nx,), physical units.
        """
        d = self.data[e]
        parts, k = [], 0
        for i in range(self.cm.nx):
            if i in d.x0_known:
                parts.append(d.x0_known[i])
            else:
                parts.append(free_scaled[k] * self.xscale[i])
                k += 1
        return ca.vertcat(*parts)

    def x0_labels(self) -> list[str]:
        """Labels of the free initial states, in the order of the decision vector.

        Returns
        -------
        list of str
            ``x0[<experiment>].<state>`` for each free initial state of each experiment.
        """
        return [f"x0[{d.name}].{self.cm.states[i]}" for d, free in zip(self.data, self.free_x0)
                for i in free]

    def single_shooting_residual(self) -> tuple[ca.MX, ca.MX, ca.MX]:
        """(θ, free x0 (scaled), residual) with every experiment simulated from its initial state.

        Returns
        -------
        theta : casadi.MX
            Symbol of the scaled free parameters, shape (n θ,).
        x0_free : casadi.MX
            Symbol of every experiment's free initial states (scaled), concatenated.
        residual : casadi.MX
            The weighted residual of all experiments, concatenated.
        """
        theta = ca.MX.sym("theta", self.layout.size)
        x0_free = ca.MX.sym("x0", sum(len(f) for f in self.free_x0))
        res, k = [], 0
        for e in range(len(self.data)):
            n_free = len(self.free_x0[e])
            x0 = self.assemble_x0(e, x0_free[k:k + n_free])
            k += n_free
            p = self.layout.full(e, theta)
            res.append(self.residual_of(e, self.outputs_of(e, self.trajectory(e, x0, p), p)))
        return theta, x0_free, ca.vertcat(*res)

    def simulate(self, theta_phys: np.ndarray, x0s: list[np.ndarray]) -> list[tuple[np.ndarray, np.ndarray]]:
        """Numeric (states, outputs) per experiment for physical θ and full initial states.

        The last few are remembered: a fit simulates the initial guess for its pre-fit check, its
        nodes and its state-size check, and the solution for its residuals and diagnostics. A
        remembered failure is reported again, as the simulation would.

        Parameters
        ----------
        theta_phys : numpy.ndarray
            The physical free parameters, shape (n θ,).
        x0s : list of numpy.ndarray
            Per experiment, the full initial state, shape (nx,).

        Returns
        -------
        list of tuple of (numpy.ndarray, numpy.ndarray)
            Per experiment, states (nx × N; NaN where the integrator failed) and outputs (ny × N).
        """
        theta_phys = np.asarray(theta_phys, dtype=float)
        x0s = [np.asarray(x0, dtype=float) for x0 in x0s]
        key = theta_phys.tobytes() + b"".join(x0.tobytes() for x0 in x0s)
        if key in self._simulated:
            out, failures = self._simulated[key]
            self.simulation_failures.extend(failures)
            return [(xs.copy(), ys.copy()) for xs, ys in out]
        before = len(self.simulation_failures)
        out = []
        theta_s = theta_phys / self.layout.scale
        for e in range(len(self.data)):
            p = np.asarray(self.layout.full(e, theta_s), dtype=float)
            xs = self.numeric_trajectory(e, x0s[e], p)
            ys = self.numeric_outputs(e, xs, p)
            out.append((xs, ys))
        self._simulated[key] = ([(xs.copy(), ys.copy()) for xs, ys in out], self.simulation_failures[before:])
        while len(self._simulated) > 4:
            self._simulated.popitem(last=False)
        return out


def _sensitivity_functions(cm: CompiledModel, step: ca.Function, options: FitOptions):
    sym = ca.MX.sym if not integrator_of(options).symbolic and cm.model.discrete is None else ca.SX.sym
    x, u0, u1 = sym("x", cm.nx), sym("u0", cm.nu), sym("u1", cm.nu)
    p, t0, dt = sym("p", cm.np), sym("t0"), sym("dt")
    xn = step(x, u0, u1, p, t0, dt)
    step_sens = ca.Function("greyfit_step_sens", [x, u0, u1, p, t0, dt],
                            [xn, ca.jacobian(xn, x), ca.jacobian(xn, p)])
    xs, us = ca.SX.sym("x", cm.nx), ca.SX.sym("u", cm.nu)
    ps, ts = ca.SX.sym("p", cm.np), ca.SX.sym("t")
    y = cm.output(xs, us, ps, ts)
    out_sens = ca.Function("greyfit_out_sens", [xs, us, ps, ts],
                           [y, ca.jacobian(y, xs), ca.jacobian(y, ps)])
    return step_sens, out_sens


def _dense_outputs(fn: ca.Function) -> tuple[list, list]:
    """(inputs, outputs) of `fn` with every output densified (a Jacobian with structural zeros is
    reshaped per sample by its callers)."""
    ins = [ca.SX.sym(fn.name_in(i), fn.sparsity_in(i)) for i in range(fn.n_in())]
    return ins, [ca.densify(o) for o in fn(*ins)]


def _first_line(exc: Exception) -> str:
    text = str(exc).strip().splitlines()
    return text[0][:200] if text else type(exc).__name__


def x0_reader(oem: OutputErrorModel, offset: int, stride_of):
    """A function that reads each experiment's initial states from the NLP's decision vector.

    Parameters
    ----------
    oem : OutputErrorModel
        The output-error model (which initial states are known, their scales).
    offset : int
        Index in the decision vector where the experiments' entries begin.
    stride_of : callable
        int -> int: the position of experiment e's free initial states relative to `offset`.

    Returns
    -------
    callable
        w -> list of dict, per experiment state name -> initial value (physical units): the known
        values as given, the free ones read from `w` and unscaled.
    """
    def read(w: np.ndarray) -> list[dict[str, float]]:
        result = []
        for e, d in enumerate(oem.data):
            start = offset + stride_of(e)
            x0 = {}
            k = 0
            for i, s in enumerate(oem.cm.states):
                if i in d.x0_known:
                    x0[s] = d.x0_known[i]
                else:
                    x0[s] = float(w[start + k] * oem.xscale[i])
                    k += 1
            result.append(x0)
        return result
    return read


def sensitivity_jacobian(oem: OutputErrorModel, theta_s: np.ndarray, x0s: list[dict[str, float]],
                         w: np.ndarray | None = None):
    """(J, r, output index of each row) of the single-shooting residual w.r.t. [θ, free x0] (scaled).

    Forward sensitivities S_{k+1} = A_k S_k + B_k are propagated in numpy from per-step Jacobians
    evaluated by one mapped call: much cheaper than differentiating the whole MX graph, and the
    same quantity (the constrained multiple-shooting problem reduced to θ and x0). Where the
    structured formulation applies, the same recursion runs as one compiled pass instead.

    Parameters
    ----------
    oem : OutputErrorModel
        The output-error model; a failure of the sensitivities is noted in `oem.simulation_failures`.
    theta_s : numpy.ndarray
        The scaled free parameters, shape (n θ,).
    x0s : list of dict
        Per experiment, state name -> initial value.
    w : numpy.ndarray or None, optional
        The solve's decision vector at this point, when it is the solve's optimum (a single-shooting
        solve's last pass already holds the rows there).

    Returns
    -------
    jac : numpy.ndarray
        Jacobian of the weighted residual, shape (rows, n θ + free initial states); NaN where the
        sensitivities failed.
    res : numpy.ndarray
        The weighted residual (y_sim − y) at the measured samples, sample-major.
    groups : numpy.ndarray
        The output index of each row.
    """
    if shooting_structured.supports(oem, single=True):
        return shooting_structured.condensed_jacobian(oem, theta_s, x0s, w)
    cm, layout = oem.cm, oem.layout
    step_sens, out_sens = oem.sensitivity_functions()
    n_theta = layout.size
    n_free = sum(len(f) for f in oem.free_x0)
    blocks, resids, groups, col = [], [], [], n_theta
    for e, d in enumerate(oem.data):
        p = np.asarray(layout.full(e, theta_s), dtype=float).ravel()
        x0 = np.array([x0s[e][s] for s in cm.states])
        states = oem.numeric_trajectory(e, x0, p)
        n = d.n
        u0, u1, t0, dt = oem.step_inputs(d, 0, n - 1)
        try:
            _, a, b = step_sens.map(n - 1)(states[:, :-1], u0, u1, np.repeat(p[:, None], n - 1, 1), t0, dt)
        except RuntimeError as exc:   # the integrator's sensitivities failed: no Jacobian
            oem.simulation_failures.append(f"sensitivities of experiment '{d.name}' failed ({_first_line(exc)})")
            nan = np.full((cm.nx, (n - 1) * cm.nx), np.nan)
            a, b = nan, np.full((cm.nx, (n - 1) * cm.np), np.nan)
        a = np.array(a).reshape(cm.nx, n - 1, cm.nx).transpose(1, 0, 2)
        b = np.array(b).reshape(cm.nx, n - 1, cm.np).transpose(1, 0, 2) @ layout.matrix[e]
        y, hx, hp = oem.output_jacobians(e, states, p)
        hp = hp @ layout.matrix[e]
        sens = np.zeros((n, cm.nx, n_theta + n_free))
        for k, i in enumerate(oem.free_x0[e]):
            sens[0, i, col + k] = oem.xscale[i]
        col += len(oem.free_x0[e])
        for k in range(n - 1):
            sens[k + 1] = a[k] @ sens[k]
            sens[k + 1, :, :n_theta] += b[k]
        jy = np.einsum("kox,kxc->koc", hx, sens)
        jy[:, :, :n_theta] += hp
        mask = d.mask.T                            # (n, ny), sample-major like the residual
        wts = np.broadcast_to(oem.weights, (n, cm.ny))
        blocks.append((jy * wts[:, :, None])[mask])
        resids.append((wts * (y.T - d.y.T))[mask])
        groups.append(np.broadcast_to(np.arange(cm.ny), (n, cm.ny))[mask])
    return np.vstack(blocks), np.concatenate(resids), np.concatenate(groups)
