"""Shape first: the missing term estimated without assuming its form.

For each state equation i (and each output path j), a disturbance d(t) is added to the fitted model
(ẋ_i = f_i(x, u, θ̂) + d, or y_j = h_j + d) and estimated from the output records by a Kalman
smoother with d a random walk (`shape_kalman`): the regularised output-error estimate of a
piecewise-constant d per sample whose smoothness penalty (the random walk's intensity) is chosen by
maximum likelihood rather than fixed. The smoother also gives the unmeasured states the disturbance
implies. Around the first estimate the model is linearised again and smoothed once more (an iterated
extended smoother, i.e. Gauss-Newton on the MAP problem), so a large missing term is not judged on
the tangent of a wrong trajectory.

The channels compete by their likelihood: with one output the disturbances of different equations
are not separately identifiable, but the one on the right equation is the smoothest that explains the
data, which is what the likelihood of a random walk rewards. Each channel's d̂ is then related to the
states, inputs and their simple combinations (`shape_relate`): which variable a smooth function of
explains most of d̂, and how much.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from greyfit.schemas.discovery import Discrepancy, DiscrepancyEquation
from greyfit.schemas.fit import FitRequest, FitResult
from greyfit.solvers.discovery.shape_kalman import Linearised, best_intensity, imprint, log_likelihood, smooth
from greyfit.solvers.discovery.shape_relate import (
    MAX_PUBLIC_SAMPLES,
    ShapeEstimate,
    candidate_variables,
    public_samples,
    relate,
    thinning,
)
from greyfit.solvers.dynamics.integration import make_step
from greyfit.solvers.errors import FitError
from greyfit.solvers.methods.shooting import OutputErrorModel
from greyfit.solvers.screening.screening import fitted_values

PRIOR_SCALE = 1e2        # prior std of z_0 in units of (state scale × σ): diffuse against the data
REFINE_CHANNELS = 2      # the best channels relinearised about their first estimate
RELATED_CHANNELS = 3     # the best channels related to the states and inputs
MAX_DIRECT_PATHS = 3     # up to this many outputs, every output path is a channel
MIN_SAMPLES = 20         # shorter records: no shape (the smoother's prior would dominate)


@dataclass
class Track:
    """One experiment's trajectory to linearise about: states (nx, n) and disturbance (n,)."""

    x: np.ndarray
    d: np.ndarray


@dataclass
class Channel:
    name: str                   # a state (equation) or "output y"
    index: int
    on_output: bool
    log_likelihood: float = -np.inf
    q: float = 0.0
    sigma2: float = 0.0
    tracks: list[Track] = field(default_factory=list)
    lins: list = field(default_factory=list)   # the last linearisations smoothed on (for `imprint`)
    explained: float = 0.0      # share of the weighted output residual's sum of squares it removes
    residual_rms: dict = field(default_factory=dict)


class ShapeModel:
    """The fitted model with a held disturbance on ẋ, its step and Jacobians, per experiment."""

    def __init__(self, request: FitRequest, fit: FitResult):
        cm, data, layout, theta_s, x0s = fitted_values(request, fit)
        self.cm, self.data = cm, data
        self.oem = OutputErrorModel(cm, data, layout, request.options)
        self.weights = self.oem.weights
        self.params = [np.asarray(layout.full(e, theta_s), dtype=float).ravel() for e in range(len(data))]
        self.simulated = [self.oem.numeric_states(e, np.array([x0s[e][s] for s in cm.states]), self.params[e])
                          for e in range(len(data))]
        self._step = self._disturbed_step(request)
        _, self._out_sens = self.oem.sensitivity_functions()

    def _disturbed_step(self, request: FitRequest) -> ca.Function:
        from types import SimpleNamespace
        cm = self.cm
        x, u, d = ca.SX.sym("x", cm.nx), ca.SX.sym("u", cm.nu), ca.SX.sym("d", cm.nx)
        p, t = ca.SX.sym("p", cm.np), ca.SX.sym("t")
        rhs = ca.Function("rhs_d", [x, ca.vertcat(u, d), p, t], [cm.rhs(x, u, p, t) + d])
        # a stand-in model (make_step reads rhs, nx, nu, np and model), as scoring_outputs builds one
        stand_in = SimpleNamespace(rhs=rhs, nx=cm.nx, nu=cm.nu + cm.nx, np=cm.np, model=cm.model)
        step = make_step(stand_in, request.options)  # type: ignore[arg-type]
        xs, u0, u1, ds = ca.SX.sym("x", cm.nx), ca.SX.sym("u0", cm.nu), ca.SX.sym("u1", cm.nu), ca.SX.sym("d", cm.nx)
        ps, t0, dt = ca.SX.sym("p", cm.np), ca.SX.sym("t0"), ca.SX.sym("dt")
        # d held over the interval whatever the inputs' interpolation: the same d in u0 and u1
        xn = step(xs, ca.vertcat(u0, ds), ca.vertcat(u1, ds), ps, t0, dt)
        return ca.Function("shape_step", [xs, u0, u1, ds, ps, t0, dt],
                           [xn, ca.jacobian(xn, xs), ca.jacobian(xn, ds)])

    def linearise(self, e: int, ch: Channel, track: Track) -> Linearised:
        """The disturbed model linearised along a trajectory, in the smoother's form.

        Parameters
        ----------
        e : int
            Index of the experiment.
        ch : Channel
            Where the disturbance enters (a state equation or an output path).
        track : Track
            The trajectory (states (nx, n), disturbance (n,)) to linearise about.

        Returns
        -------
        Linearised
            Per-sample A_k, the disturbance column b_k (in units of `disturbance_scale`), the gap c_k,
            weighted H_k, the weighted output residual with its mask, and the diffuse prior of z_0.
        """
        cm, d = self.cm, self.data[e]
        nx, ny, n = cm.nx, cm.ny, d.n
        u0, u1, t0, dt = self.oem.step_inputs(d, 0, n - 1)
        dist = np.zeros((nx, n))
        if not ch.on_output:
            dist[ch.index] = track.d
        xn, a, bd = self._step.map(n - 1)(track.x[:, :-1], u0, u1, dist[:, :-1],
                                          np.repeat(self.params[e][:, None], n - 1, 1), t0, dt)
        a = np.array(a).reshape(nx, n - 1, nx)
        bd = np.array(bd).reshape(nx, n - 1, nx)
        vec_a = np.zeros((nx * nx, n))
        vec_a[:, :-1] = a.transpose(2, 0, 1).reshape(nx * nx, n - 1)
        s = disturbance_scale(self, ch)   # the smoother's d is in units of s: one grid of q fits all
        b = np.zeros((nx, n))
        if not ch.on_output:
            b[:, :-1] = s * bd[:, :, ch.index]
        c = np.zeros((nx + 1, n))
        c[:nx, :-1] = np.array(xn) - track.x[:, 1:]
        c[nx, :-1] = (track.d[:-1] - track.d[1:]) / s
        y, hx, _ = self._out_sens.map(n)(track.x, d.u, np.repeat(self.params[e][:, None], n, 1), d.t[None, :])
        y = np.array(y)
        hx = np.array(hx).reshape(ny, n, nx)
        hd = np.zeros(ny)
        if ch.on_output:
            hd[ch.index] = self.weights[ch.index] * s
            y[ch.index] += track.d
        w = self.weights[:, None]
        r = w * (d.y - y)
        mask = np.isfinite(r)
        vec_h = (w[:, :, None] * hx).transpose(2, 0, 1).reshape(ny * nx, n)
        return Linearised(a=vec_a, b=b, c=c, h=vec_h, hd=hd, r=np.where(mask, r, 0.0), mask=mask.astype(float),
                          p0=self._prior(e, ch))

    def _prior(self, e: int, ch: Channel) -> np.ndarray:
        x = self.simulated[e]
        sx = np.maximum(np.std(x, axis=1), 1e-6 * (np.max(np.abs(x), axis=1) + 1.0))
        return (PRIOR_SCALE * np.append(sx, 1.0)) ** 2

    def residual(self, e: int, ch: Channel, track: Track) -> np.ndarray:
        """Weighted output residual (ny, n) of the disturbed model along a trajectory.

        Parameters
        ----------
        e : int
            Index of the experiment.
        ch : Channel
            Where the disturbance enters (on an output path it is added to that output).
        track : Track
            The trajectory.

        Returns
        -------
        numpy.ndarray
            (ny, n) weighted measured − modelled outputs (NaN where not measured).
        """
        d = self.data[e]
        y = self.oem.numeric_outputs(e, track.x, self.params[e])
        if ch.on_output:
            y = y.copy()
            y[ch.index] += track.d
        return self.weights[:, None] * (d.y - y)


def disturbance_scale(sm: ShapeModel, ch: Channel) -> float:
    """The size d is measured in: the output's spread, or the RMS rate of change of the state
    (over all experiments, so that one intensity serves them all).

    Parameters
    ----------
    sm : ShapeModel
        The fitted model and its simulations.
    ch : Channel
        The channel.

    Returns
    -------
    float
        1/weight of the output for an output path; else the RMS of the state's rate of change along
        the simulations (1 when that is zero or not finite).
    """
    if ch.on_output:
        return float(1.0 / sm.weights[ch.index])
    rates = np.concatenate([np.diff(x[ch.index]) / np.diff(d.t) for x, d in zip(sm.simulated, sm.data)])
    rms = float(np.sqrt(np.mean(rates ** 2)))
    return rms if np.isfinite(rms) and rms > 0 else 1.0


def channels(sm: ShapeModel) -> list[Channel]:
    """Every state equation, and the output paths: all of them with a few outputs; with many, only
    outputs that are not a state measured directly (that state's equation stands in for it, and each
    channel costs a smoother whose work grows with outputs × states²).

    Parameters
    ----------
    sm : ShapeModel
        The fitted model.

    Returns
    -------
    list of Channel
        One per state equation, then one per output path kept (all when ny ≤ `MAX_DIRECT_PATHS`).
    """
    cm = sm.cm
    out = [Channel(name=s, index=i, on_output=False) for i, s in enumerate(cm.states)]
    paths = [j for j, o in enumerate(cm.outputs) if cm.ny <= MAX_DIRECT_PATHS or o not in cm.direct_outputs]
    return out + [Channel(name=f"output {cm.outputs[j]}", index=j, on_output=True) for j in paths]


@dataclass
class ShapeResult:
    """Every channel's estimate (most likely first), the noise level, and the public form."""

    estimates: list[ShapeEstimate]
    noise_level: dict[str, float]
    public: Discrepancy


def _estimate_channel(sm: ShapeModel, ch: Channel, q: float | None = None) -> None:
    """Smooth once about the fitted simulation (choosing q), then about that estimate."""
    if not ch.tracks:
        ch.tracks = [Track(x=x.copy(), d=np.zeros(x.shape[1])) for x in sm.simulated]
    lins = [sm.linearise(e, ch, tr) for e, tr in enumerate(ch.tracks)]
    if q is None:
        ch.q, ch.log_likelihood, ch.sigma2 = best_intensity(lins)
    else:
        ch.q = q
        ch.log_likelihood, ch.sigma2 = log_likelihood(lins, q)
    s = disturbance_scale(sm, ch)
    nx = sm.cm.nx
    ch.lins = lins
    for tr, lin in zip(ch.tracks, lins):
        z = smooth(lin, ch.q)
        tr.x = tr.x + z[:nx]
        tr.d = tr.d + s * z[nx]


def _score_channel(sm: ShapeModel, ch: Channel) -> None:
    before = after = 0.0
    for e, tr in enumerate(ch.tracks):
        r0 = sm.weights[:, None] * (sm.data[e].y - sm.oem.numeric_outputs(e, sm.simulated[e], sm.params[e]))
        r1 = sm.residual(e, ch, tr)
        before += float(np.nansum(r0 ** 2))
        after += float(np.nansum(r1 ** 2))
    ch.explained = 1.0 - after / before if before > 0 else 0.0


def _to_estimate(sm: ShapeModel, ch: Channel, related: bool = True) -> ShapeEstimate:
    cm = sm.cm
    states = [tr.x for tr in ch.tracks]
    inputs = [d.u for d in sm.data]
    est = ShapeEstimate(equation=ch.name, d=[tr.d for tr in ch.tracks], time=[d.t for d in sm.data],
                        variables=candidate_variables(cm.states, states, cm.inputs, inputs),
                        linear=[np.vstack([x, u]).T for x, u in zip(states, inputs)],
                        linear_names=list(cm.states) + list(cm.inputs),
                        log_likelihood=ch.log_likelihood, q=ch.q, residual_share=ch.explained)
    if ch.lins:
        scale, lins, q = disturbance_scale(sm, ch), ch.lins, ch.q
        est.imprint = lambda cols: [s_ * scale for s_ in imprint(lins, q, [c / scale for c in cols])]
    if related:
        relate(est)
    return est


def estimate_shape(request: FitRequest, fit: FitResult) -> ShapeResult:
    """The missing term's shape at a fit: a disturbance on each equation and output path in turn.

    Parameters
    ----------
    request : FitRequest
        The request the fit answered (model, experiments, options: the integrator is the fit's).
    fit : FitResult
        A converged fit of it (parameters and initial states are read from it).

    Returns
    -------
    ShapeResult
        `estimates`: one `ShapeEstimate` per channel, the most likely first (for `shape_agreement`);
        `noise_level`: measurement-noise std per output with the most likely channel;
        `public`: the same as the schema's `Discrepancy`.

    Raises
    ------
    RuntimeError
        Where the fitted model cannot be simulated or linearised.
    """
    sm = ShapeModel(request, fit)
    chans = channels(sm)
    for ch in chans:
        _estimate_channel(sm, ch)
    chans.sort(key=lambda c: c.log_likelihood, reverse=True)
    for ch in chans[:REFINE_CHANNELS]:   # relinearised about the first estimate, q kept
        _estimate_channel(sm, ch, ch.q)
    for ch in chans:
        _score_channel(sm, ch)
    chans.sort(key=lambda c: c.log_likelihood, reverse=True)
    sigma = float(np.sqrt(chans[0].sigma2))
    noise = {o: sigma / float(sm.weights[j]) for j, o in enumerate(sm.cm.outputs)}
    estimates = [_to_estimate(sm, ch, related=i < RELATED_CHANNELS) for i, ch in enumerate(chans)]
    return ShapeResult(estimates=estimates, noise_level=noise, public=to_public(sm, estimates, chans[0], noise))


def to_public(sm: ShapeModel, estimates: list[ShapeEstimate], best: Channel, noise: dict) -> Discrepancy:
    """The shape step's result as the schema's `Discrepancy`, series thinned.

    Parameters
    ----------
    sm : ShapeModel
        The fitted model and its data.
    estimates : list of ShapeEstimate
        Every channel's estimate, most likely first.
    best : Channel
        The most likely channel (its smoothed states are reported).
    noise : dict
        Output -> measurement-noise std.

    Returns
    -------
    Discrepancy
        Per channel its likelihood, intensity, residual share and samples (with the variable and law
        where related), the noise level and the best channel's states, each series thinned to at most
        `MAX_PUBLIC_SAMPLES` per experiment.
    """
    stride = thinning(max(d.n for d in sm.data))
    names = [d.name for d in sm.data]

    def per_exp(series):
        return dict(zip(names, public_samples(series, stride)))
    equations = [DiscrepancyEquation(
        equation=est.equation, log_likelihood=float(est.log_likelihood), intensity=float(est.q),
        residual_share=float(est.residual_share), time=per_exp(est.time), samples=per_exp(est.d),
        variable=est.variable, variable_samples=per_exp(est.variables[est.variable]) if est.variable else {},
        law_samples=per_exp(est.law) if est.law else {}, law_grid=est.law_grid.tolist(),
        law_values=est.law_values.tolist(), share_explained=est.share_explained,
        alternatives=est.alternatives) for est in estimates]
    states = {name: {s: public_samples([tr.x[i]], stride)[0] for i, s in enumerate(sm.cm.states)}
              for name, tr in zip(names, best.tracks)}
    return Discrepancy(equations=equations, noise_level=noise, states=states, thinned_to=MAX_PUBLIC_SAMPLES)


def shape_at(request: FitRequest, fit: FitResult, clock) -> tuple[ShapeResult | None, str]:
    """`estimate_shape` timed as the "shape" phase; (None, why) where it cannot run.

    Parameters
    ----------
    request : FitRequest
        The request the fit answered.
    fit : FitResult
        The fit.
    clock : Clock
        The discovery budget; nothing is estimated once it is spent.

    Returns
    -------
    tuple of (ShapeResult or None, str)
        The shape and ""; or None with the reason (a difference-equation model, a record shorter than
        `MIN_SAMPLES`, a failure of the smoother), or None and "" for a failed fit or a spent budget.
    """
    if request.model.discrete is not None:
        return None, "no shape estimated: the model is a difference equation (the shape step needs an ODE)"
    if fit.quality == "failed" or not clock.allows():
        return None, ""
    if min(len(e.time) for e in request.experiments) < MIN_SAMPLES:
        return None, f"no shape estimated: a record has fewer than {MIN_SAMPLES} samples"
    with clock.phase("shape"):
        try:
            shape = estimate_shape(request, fit)
        except (FitError, RuntimeError, ValueError, np.linalg.LinAlgError) as exc:
            return None, f"no shape estimated: {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}"
    if not _finite(shape):
        return None, "no shape estimated: the smoother did not stay finite on these records"
    return shape, ""


def _finite(shape: ShapeResult) -> bool:
    numbers = [e.log_likelihood for e in shape.estimates] + list(shape.noise_level.values())
    return bool(np.all(np.isfinite(numbers)) and all(np.all(np.isfinite(d)) for e in shape.estimates for d in e.d))
