"""Measurement noise in recursive least squares: the colour it gives the equation error.

RLS regresses x[k+1] on Φ_k η. When the noise is on the *measured signal* v (the RL circuit of the
model reference adaptive systems chapter:
i is measured, the equation is exact), the equation error is not white but the moving average

    e_k = v_{k+1} − Σ_j (∂f/∂x_j) v_{k−lag_j},

the delay states (y_1 = y[k−1], …) bringing older samples of the same signal. With fast sampling
(∂f/∂y ≈ 1) the terms nearly cancel, so σ²P — which assumes a white e — overstates the spread of
θ̂ several times (×4 on the RL circuit at λ = 0.98, measured). The exact covariance of the noise
part of θ̂_k = P_k Σ λ^{k−i} Φ_iᵀ y_i is σ_v² P_k S_k P_k with

    S_k = Σ_m h_m h_mᵀ,   h_m = Σ_{i: e_i contains v_m} λ^{k−i} Φ_iᵀ c_{i,m},

c the coefficients above, taken from the model at the current estimate η̂ — not from residual
autocorrelations, which cannot resolve a near-cancellation over a 1/(1−λ)-sample window.
`NoiseCovariance` keeps S_k recursively: h of noise samples that can still receive terms are
"open", the others are folded into one matrix; every step multiplies them by λ (resp. λ²).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import casadi as ca
import numpy as np

from greyfit.solvers.errors import DataError
from greyfit.solvers.model.discrete import delay_sources
from greyfit.solvers.model.reparametrize import LinearForm


@dataclass
class MeasurementNoise:
    """e at update i = Σ_d c_d(η) v[sample_i + d] (one equation, one noisy measured signal)."""

    samples: np.ndarray                 # (M,) sample index of every RLS update
    offsets: np.ndarray                 # (D,) d: +1 for the measured next value, −lag for the states
    gains: ca.Function                  # η (scaled) -> c (D,)
    signal: str                         # the output whose noise this is

    def coefficients(self, eta: np.ndarray) -> np.ndarray:
        """The moving-average coefficients c_d(η) at an estimate.

        Parameters
        ----------
        eta : numpy.ndarray
            (nη,) estimate, scaled units.

        Returns
        -------
        numpy.ndarray
            (D,) coefficients, one per entry of `offsets`.
        """
        return np.array(self.gains(eta), dtype=float).ravel()


@dataclass
class NoiseCovariance:
    """S_k of the module docstring, updated once per RLS step."""

    noise: MeasurementNoise
    lam: float
    n: int
    closed: np.ndarray = field(init=False)
    open: dict[int, np.ndarray] = field(default_factory=dict)
    gain_sq: float = 1.0

    def __post_init__(self):
        self.closed = np.zeros((self.n, self.n))

    def update(self, k: int, phi_row: np.ndarray, eta: np.ndarray) -> np.ndarray:
        """Add update k (regressor row Φ_k, estimate η̂_k) and return S_k.

        Parameters
        ----------
        k : int
            Index of the RLS update (row of `noise.samples`).
        phi_row : numpy.ndarray
            (nη,) regressor row Φ_k of the one estimated equation.
        eta : numpy.ndarray
            (nη,) estimate after the update, scaled units; the coefficients are taken there.

        Returns
        -------
        numpy.ndarray
            (nη, nη) S_k; `gain_sq` is set to Σ c_d² at the same time.
        """
        c = self.noise.coefficients(eta)
        self.gain_sq = float(c @ c)
        self.closed *= self.lam * self.lam
        for m in self.open:
            self.open[m] = self.open[m] * self.lam
        sample = int(self.noise.samples[k])
        for d, cd in zip(self.noise.offsets, c):
            m = sample + int(d)
            self.open[m] = self.open.get(m, 0.0) + phi_row * cd
        last = sample + int(np.min(self.noise.offsets))   # older samples get no more terms
        for m in [m for m in self.open if m < last]:
            h = self.open.pop(m)
            self.closed += np.outer(h, h)
        s = self.closed.copy()
        for h in self.open.values():
            s += np.outer(h, h)
        return s


def _source(cm, state: int, sources: dict[int, tuple[str, int]]) -> tuple[str, int, int] | None:
    """(kind, index, lag) of the measured signal a state is, following delay chains; None if unknown."""
    lag = 0
    for _ in range(cm.nx + 1):
        outs = [o for o, s in cm.direct_outputs.items() if s == cm.states[state]]
        if outs:
            return ("output", cm.outputs.index(outs[0]), lag)
        if state not in sources:
            return None
        kind, j = sources[state]
        lag += 1
        if kind == "input":
            return ("input", j, lag)
        state = j
    return None


def measurement_noise(form: LinearForm, equations: list[int], rows: np.ndarray) -> MeasurementNoise:
    """The moving-average map of measurement noise into the one estimated equation; errors name the field.

    Parameters
    ----------
    form : LinearForm
        The model in its linear coefficients η.
    equations : list of int
        Indices of the estimated state equations (exactly one is accepted).
    rows : numpy.ndarray
        (M,) sample index of every RLS update.

    Returns
    -------
    MeasurementNoise
        The sample offsets, the coefficient Function η -> c and the name of the noisy output.

    Raises
    ------
    DataError
        On `options.rls.noise` when the model is continuous-time, more than one equation is estimated,
        the equation's state is not measured directly, the equation is not linear in the states, or it
        reads a state that is neither measured nor a delay of a measured signal, or two measured signals.
    """
    cm = form.cm
    if cm.model.discrete is None:
        raise DataError("the measurement noise model is for discrete-time models (continuous ones see the "
                        "noise through the derivative filter); use a prefilter instead", "options.rls.noise")
    if len(equations) != 1:
        raise DataError(f"the measurement noise model takes one estimated equation ({len(equations)} here)",
                        "options.rls.noise")
    eq = equations[0]
    direct = {cm.states.index(s) for s in cm.direct_outputs.values()}
    if eq not in direct:
        raise DataError(f"state '{cm.states[eq]}' is not measured directly", "options.rls.noise")
    sources = delay_sources(cm)
    x, u, t = ca.SX.sym("x", cm.nx), ca.SX.sym("u", cm.nu), ca.SX.sym("t")
    eta = ca.SX.sym("eta", form.layout.size)
    p = ca.DM(form.layout.offset) + ca.DM(form.layout.matrix[0]) @ eta
    jx = ca.jacobian(cm.rhs(x, u, p, t)[eq], x)
    if ca.depends_on(jx, ca.vertcat(x, u, t)):
        raise DataError("the measurement noise model needs the equation linear in the states",
                        "options.rls.noise")
    signal = _source(cm, eq, sources)
    if signal is None:   # a directly measured state is its own source; kept for a clear error all the same
        raise DataError(f"state '{cm.states[eq]}' is not measured directly", "options.rls.noise")
    offsets, gains = [1], [ca.SX(1)]
    for j in range(cm.nx):
        if not ca.depends_on(jx[j], eta) and float(ca.evalf(jx[j])) == 0.0:
            continue
        src = _source(cm, j, sources)
        if src is None:
            raise DataError(f"state '{cm.states[j]}' is neither measured nor a delay of a measured signal",
                            "options.rls.noise")
        if src[0] == "input":
            continue                                   # inputs are taken as noise-free
        if src[:2] != signal[:2]:
            raise DataError("the measurement noise model takes one noisy measured signal; this equation "
                            f"reads '{cm.outputs[signal[1]]}' and '{cm.outputs[src[1]]}'", "options.rls.noise")
        offsets.append(-src[2])
        gains.append(-jx[j])
    return MeasurementNoise(np.asarray(rows, dtype=int), np.array(offsets, dtype=int),
                            ca.Function("noise_gains", [eta], [ca.vertcat(*gains)]), cm.outputs[signal[1]])
