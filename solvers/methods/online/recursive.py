"""Recursive least squares (model reference adaptive systems chapter, 7.4) and the persistent-excitation report.

The regression y_k = Φ_k η + e_k comes from equation error's sample Jacobian (one block of rows per
sample: one row per equation with a free parameter), so continuous-time models with estimated
derivatives and discrete-time models (ARX: the one-step predictor) are handled alike.

Gain laws (λ1, λ2 of eq. 7-45):

* ``forgetting``: weighted LS with forgetting factor λ (eqs. 7-38/7-39), λ1 = λ, λ2 = 1;
* ``decreasing_gain``: λ = 1, ordinary least squares;
* ``constant_trace``: λ1(k) = λ2(k) chosen so that trace P stays at trace P₀ (Landau);
* ``constant_gain``: P stays γI (λ1 = 1, λ2 = 0): a normalised gradient law.

The ±2σ band is the covariance of θ̂_k = P_k Σ λ^{k−i} Φ_iᵀ y_i under white equation error,
σ̂² P_k (Σ λ^{2(k−i)} Φ_iᵀΦ_i) P_k (σ̂² from the forgetting-weighted a-posteriori residuals); the
textbook σ̂²P_k equals it for λ = 1 but is ~(1 + λ) times too large for λ < 1 (coverage of the
truth ~100 % instead of 95 %, measured). With `noise: "measurement"` the equation error is the
moving average of the output noise (`solvers.rls_noise`). P is no covariance for the
constant-trace and constant-gain laws, so no band is given there.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from greyfit.schemas.online import ExcitationReport, RlsOptions
from greyfit.solvers.methods.online.rls_noise import MeasurementNoise, NoiseCovariance

PE_RELATIVE_EIGENVALUE = 1e-10
RANK_RELATIVE_EIGENVALUE = 1e-10
PE_MAX_ORDER = 40
EXACT_START_EIGENVALUE = 1e-12   # equilibrated information matrix: invertible enough to start from


@dataclass
class OnlineRun:
    """Estimates after every update (scaled units) and what they were made from."""

    estimates: np.ndarray          # (M, nη)
    covariances: np.ndarray | None  # (M, nη, nη) or None
    innovations: np.ndarray        # (M, neq) a-priori errors y_k − Φ_k η_{k-1}
    label: str
    window: int                    # effective number of samples remembered
    memory: float                  # λ for the excitation weighting (1: whole record)
    measured: np.ndarray | None = None   # (neq, M) what the innovations are errors of (default ẋ / x[k+1])
    residual_weighted: bool = True       # innovations carry equation error's weights


@dataclass
class _ExactStart:
    """Weighted sums of the first rows, kept until their information matrix is invertible.

    Then the estimate and P are set to the weighted least-squares solution of those rows,
    θ̂ = (Σ λ^{k−i} ΦᵢᵀΦᵢ)⁻¹ Σ λ^{k−i} Φᵢᵀyᵢ and P = (Σ λ^{k−i} ΦᵢᵀΦᵢ)⁻¹: the recursion starts at
    k = n as the RLS derivation of the model reference adaptive systems chapter prescribes, so for
    λ = 1 every later θ̂_k equals batch least squares on the rows so far. P₀ = γI instead adds the prior
    ‖θ − θ₋₁‖²/γ, which on closely sampled, collinear regressors moves the answer by tens of percent.
    """

    n: int
    lam: float
    info: np.ndarray = field(init=False)
    rhs: np.ndarray = field(init=False)
    yy: float = 0.0

    def __post_init__(self):
        self.info, self.rhs = np.zeros((self.n, self.n)), np.zeros(self.n)

    def add(self, f: np.ndarray, y: np.ndarray) -> None:
        lam = self.lam
        self.info = lam * self.info + f.T @ f
        self.rhs = lam * self.rhs + f.T @ y
        self.yy = lam * self.yy + float(y @ y)

    def solve(self) -> tuple[np.ndarray, np.ndarray, float] | None:
        """(θ̂, P, weighted residual sum) once the equilibrated information matrix has full rank."""
        d = np.sqrt(np.diag(self.info))
        if np.any(d <= 0) or not np.all(np.isfinite(d)):
            return None
        scaled = self.info / np.outer(d, d)
        ev = np.linalg.eigvalsh(scaled)
        if ev[0] <= EXACT_START_EIGENVALUE * ev[-1]:
            return None
        p = np.linalg.inv(scaled) / np.outer(d, d)
        eta = p @ self.rhs
        ss = max(self.yy - float(eta @ self.rhs), 0.0)
        return eta, 0.5 * (p + p.T), ss


def recursive_least_squares(y: np.ndarray, phi: np.ndarray, eta0: np.ndarray, opts: RlsOptions,
                            noise: MeasurementNoise | None = None) -> OnlineRun:
    """Run RLS over the rows; y (M, neq), phi (M, neq, nη), eta0 (nη,) initial estimate.

    Parameters
    ----------
    y : numpy.ndarray
        (M, neq) measurements of the M updates (a block of neq rows per sample).
    phi : numpy.ndarray
        (M, neq, nη) regressors of the M updates.
    eta0 : numpy.ndarray
        (nη,) initial estimate θ̂₋₁ (scaled units; the guess).
    opts : RlsOptions
        Forgetting factor, gain law, initial covariance γ (P₀ = γI), initialisation. With
        ``initialisation="exact"`` (the forgetting and decreasing-gain laws) γI only serves the first
        rows, until their information matrix is invertible; from there θ̂ is weighted least squares.
    noise : MeasurementNoise or None
        Measurement noise map (`solvers.methods.online.rls_noise`); None: white equation error.

    Returns
    -------
    OnlineRun
        Estimates (M, nη) after every update, their covariances (M, nη, nη) for the forgetting and
        decreasing-gain laws (None for constant trace and constant gain), the a-priori innovations
        (M, neq), a label naming the gain law, the effective window 1/(1 − λ) (at most M; M for λ = 1)
        and λ.
    """
    m, neq, n = phi.shape
    law = opts.gain_law
    lam = opts.forgetting if law == "forgetting" else 1.0
    eta = np.array(eta0, dtype=float)
    p = opts.initial_covariance * np.eye(n)
    trace0 = np.trace(p)
    eye = np.eye(neq)
    estimates = np.empty((m, n))
    covs = np.empty((m, n, n)) if law in ("forgetting", "decreasing_gain") else None
    exact = _ExactStart(n, lam) if covs is not None and opts.initialisation == "exact" else None
    innovations = np.empty((m, neq))
    ss, dof = 0.0, 0.0
    q = np.zeros((n, n))       # Σ λ^{2(k−i)} ΦᵢᵀΦᵢ: the information the noise brings (sandwich)
    coloured = None if noise is None or covs is None else NoiseCovariance(noise, lam, n)
    for k in range(m):
        f = phi[k]
        e = y[k] - f @ eta
        pf = p @ f.T                                     # (n, neq)
        s = (lam if covs is not None else 1.0) * eye + f @ pf
        gain = np.linalg.solve(s, pf.T).T                # P Φᵀ S⁻¹
        eta = eta + gain @ e
        if law in ("forgetting", "decreasing_gain"):
            p = (p - gain @ pf.T) / lam
        elif law == "constant_trace":
            p = p - gain @ pf.T
            p *= trace0 / np.trace(p)
        p = 0.5 * (p + p.T)
        post = y[k] - f @ eta
        ss = lam * ss + float(post @ post)
        dof = lam * dof + neq
        if exact is not None:
            exact.add(f, y[k])
            start = exact.solve()
            if start is not None:
                eta, p, ss = start
                exact = None
        estimates[k] = eta
        innovations[k] = e
        if covs is not None:
            # θ̂ = P Σ λ^{k−i} Φᵢᵀ yᵢ (+ the prior): with white noise Cov = σ² P (Σ λ^{2(k−i)} ΦᵢᵀΦᵢ) P, which
            # is σ²P only for λ = 1; for λ < 1 σ²P is too large by about (1 + λ) (1.98 at λ = 0.98)
            if coloured is None:
                q = lam * lam * q + f.T @ f
                covs[k] = ss / max(dof - n, 1.0) * (p @ q @ p)
            else:    # σ_v² = var(e)/Σc²: e is the moving average Σ c_d v of the measurement noise
                s_k = coloured.update(k, f[0], eta)
                covs[k] = ss / max(dof - n, 1.0) / max(coloured.gain_sq, 1e-300) * (p @ s_k @ p)
    window = m if lam >= 1 else int(min(m, round(1 / (1 - lam))))
    label = {"forgetting": f"recursive_least_squares (forgetting factor {lam:g})",
             "decreasing_gain": "recursive_least_squares (decreasing gain, λ = 1)",
             "constant_trace": "recursive_least_squares (constant trace)",
             "constant_gain": "recursive_least_squares (constant gain)"}[law]
    return OnlineRun(estimates, covs, innovations, label, window, lam)


def pe_order(u: np.ndarray, max_order: int = PE_MAX_ORDER, spacing: int = 1) -> int:
    """Largest n for which the lagged-input matrix [u_k, u_{k-s}, ..., u_{k-(n-1)s}] has full rank.

    Full rank: the smallest eigenvalue of its Gram matrix above 1e-10 of the largest. A constant has
    order 1, a sinusoid 2, n sinusoids 2n (the model reference adaptive systems chapter: an n-th order
    plant needs n frequencies), at any lag spacing s that does not alias them; neighbouring samples of
    a finely sampled input are nearly collinear, so lags one sample apart count two slow sines in a
    short window as three (`spacing` spreads the lags over the window instead).

    Parameters
    ----------
    u : numpy.ndarray
        (N,) one input series.
    max_order : int
        Largest order tried (it is also capped so that N/2 rows remain).
    spacing : int
        Samples between the lags.

    Returns
    -------
    int
        The persistent-excitation order; 0 for an all-zero input.
    """
    u = np.asarray(u, dtype=float)
    n_max = min(max_order, u.size // 2, 1 + u.size // (2 * spacing))
    order = 0
    for n in range(1, n_max + 1):
        span = (n - 1) * spacing
        lagged = np.column_stack([u[span - j * spacing:u.size - j * spacing] for j in range(n)])
        gram = lagged.T @ lagged
        ev = np.linalg.eigvalsh(gram)
        if ev[-1] <= 0 or ev[0] <= PE_RELATIVE_EIGENVALUE * ev[-1]:
            break
        order = n
    return order


def required_order(phi: np.ndarray) -> int:
    """Persistent-excitation order the regression needs: the most coefficients one equation has.

    A regressor that is a linear filter of the inputs has rank at most the inputs' PE order, so an
    equation with n coefficients needs input of order n (an n-th order ARX model 2n: n frequencies).

    Parameters
    ----------
    phi : numpy.ndarray
        (M, neq, nη) regressors; a coefficient belongs to an equation when its column is ever nonzero there.

    Returns
    -------
    int
        The largest number of coefficients in one equation (0 for an empty regressor).
    """
    used = np.any(phi != 0, axis=0)                  # (neq, nη): which coefficients each equation has
    return int(np.max(np.sum(used, axis=1))) if used.size else 0


def _available_order(phi: np.ndarray, inputs: dict[str, np.ndarray], window: int,
                     needed: int | None) -> tuple[dict[str, int], int]:
    """(PE order of each input over the window, the order they give the regression together).

    A constant regressor column (an offset term) adds one; the inputs are then counted without
    their mean, so that a DC input and the offset are not counted twice. The lags are spread over
    the window (a quarter of it for the orders asked about: two more than the regression needs).
    """
    m = phi.shape[0]
    tail = phi[m - window:]
    # constant to rounding: the equation-error regressor carries the inputs through its smoother
    constant = bool(np.any(np.all(np.abs(tail - tail[:1]) <= 1e-9 * np.abs(tail[:1]), axis=0) & (tail[0] != 0)))
    top = min(PE_MAX_ORDER, (needed or PE_MAX_ORDER) + 2)
    spacing = max(1, window // (4 * top))
    orders = {name: pe_order(series[m - window:], top, spacing) for name, series in inputs.items()}
    if not constant:
        return orders, sum(orders.values())
    centred = sum(pe_order(_centred(series[m - window:]), top, spacing) for series in inputs.values())
    return orders, centred + 1


def _centred(u: np.ndarray) -> np.ndarray:
    """u without its mean; a constant's rounding residue (1e-16 of it) is zero, not a rich signal."""
    c = u - np.mean(u)
    return np.zeros_like(c) if np.max(np.abs(c), initial=0.0) <= 1e-9 * np.max(np.abs(u), initial=0.0) else c


def excitation_report(phi: np.ndarray, run: OnlineRun, inputs: dict[str, np.ndarray],
                      linear_regressor: bool = True) -> ExcitationReport:
    """PE order of each input and rank/condition of the regressor over the estimator's window.

    `inputs` are the input series at the updates (aligned with the rows of `phi`). When the
    regressor is a linear function of states and inputs (`linear_regressor`), the inputs' PE
    order is also compared with the order the model needs (`required_order`): a noisy regressor
    can have full rank from noise alone while the input cannot determine the coefficients.

    Parameters
    ----------
    phi : numpy.ndarray
        (M, neq, nη) regressors of the updates.
    run : OnlineRun
        The estimator's run: its `memory` λ weights the information matrix, its `window` bounds the
        samples the PE order is counted over.
    inputs : dict of str to numpy.ndarray
        Input name to its (M,) series at the updates.
    linear_regressor : bool
        Whether the regressor is a linear filter of the inputs (then the required order is compared).

    Returns
    -------
    ExcitationReport
        The window, each input's PE order, the regressor's rank, size and condition number, the required
        and available orders (None when not compared) and whether the data are persistently exciting.
    """
    m, _, n = phi.shape
    weights = run.memory ** np.arange(m - 1, -1, -1, dtype=float)
    info = np.einsum("k,kei,kej->ij", weights, phi, phi)
    d = np.sqrt(np.maximum(np.diag(info), 1e-300))
    ev = np.linalg.eigvalsh(info / np.outer(d, d))
    rank = int(np.sum(ev > RANK_RELATIVE_EIGENVALUE * ev[-1])) if ev[-1] > 0 else 0
    cond = float(ev[-1] / ev[0]) if ev[0] > 0 else None
    window = min(run.window, m)
    needed = required_order(phi) if linear_regressor and inputs else None
    orders, available = _available_order(phi, inputs, window, needed)
    enough = needed is None or available >= needed
    return ExcitationReport(window_samples=window, input_order=orders, regressor_rank=rank, regressor_size=n,
                            regressor_condition=cond, persistently_exciting=rank == n and enough,
                            required_order=needed, available_order=available if needed is not None else None)
