"""Checks of the data before fitting: information at the start, input excitation, input roughness."""
from __future__ import annotations

import functools

import numpy as np

from greyfit.schemas.fit import FitWarning
from greyfit.solvers.dynamics.integration import INTEGRATORS
from greyfit.solvers.errors import DataError
from greyfit.solvers.inference.covariance import null_directions

START_CONDITION_LIMIT = 1e10   # at the initial guess; noise-free data give ~1e-16 exact nulls
PE_MAX_ORDER = 8
PE_RATIO = 1e-6
ROUGH_INPUT = 0.5   # effective ω·Δt of an input above which first-order hold misrepresents it


def information_warnings(gram: np.ndarray, labels: list[str]) -> list[FitWarning]:
    """Condition and every null direction of JᵀJ (column-equilibrated) at the initial guess.

    Raises DataError when no column of J is nonzero: nothing at all can be identified.

    Parameters
    ----------
    gram : numpy.ndarray
        JᵀJ of the weighted residual's Jacobian J at the initial guess, shape (n_variables, n_variables).
    labels : list of str
        Name of each column of J (free parameters and initial states).

    Returns
    -------
    list of FitWarning
        An ``initial_simulation_diverged`` warning when `gram` is not finite; a ``poor_excitation``
        warning with the condition, the null directions (condition limit `START_CONDITION_LIMIT`) and
        the parameters involved; else an empty list.

    Raises
    ------
    DataError
        When every column of J is zero; names ``experiments``.
    """
    if not np.all(np.isfinite(gram)):
        return [FitWarning(code="initial_simulation_diverged",
                           message="the model's simulation at the initial guess is not finite or runs away "
                                   "(|x| > 1e12); "
                                   "the excitation could not be checked",
                           detail={})]
    norms = np.sqrt(np.maximum(np.diag(gram), 0.0))   # of J's columns
    if norms.size == 0 or np.all(norms == 0):
        raise DataError("no free parameter or initial state changes the fitted residual at the "
                        "initial guess: nothing is identifiable from these data. Excite the system "
                        "(vary the inputs) or measure an output that depends on the parameters",
                        "experiments")
    d = np.where(norms > 0, norms, 1.0)
    normed = gram / np.outer(d, d)
    eigval, eigvec = np.linalg.eigh(normed)
    zero_cols = [labels[i] for i in np.flatnonzero(norms == 0)]
    condition = float(eigval[-1] / max(eigval[0], 1e-300))
    nulls = null_directions(eigval, eigvec, labels, START_CONDITION_LIMIT)
    if not nulls and not zero_cols:
        return []
    names = sorted({n for n in zero_cols} | {lab for lab in labels for c in nulls if _mentions(c, lab)})
    return [FitWarning(
        code="poor_excitation",
        message=(f"the data do not determine every parameter at the initial guess (information "
                 f"condition {condition:.1e}); null directions: {'; '.join(nulls)}. "
                 "Excite the system more richly (steps plus several sinusoids whose summed spectrum is flat "
                 "over the band of interest, as in 'Digital simulation and parameter estimation for "
                 "multivariable systems') or fix "
                 "some of: " + ", ".join(names) + ". POST /v1/designs (greyfit design --result) computes the "
                 "input that determines them, within the limits you give"),
        detail={"condition": condition, "null_directions": nulls, "parameters": names,
                "design": {"criterion": "D", "parameters_of_interest": [n for n in names if "[" not in n]}})]


def _mentions(combination: str, label: str) -> bool:
    return any(term.split("*", 1)[-1] == label for term in combination.split())


def persistent_excitation_order(u: np.ndarray, max_order: int = PE_MAX_ORDER) -> int:
    """Largest n whose n×n (non-centred) autocovariance matrix of u is well conditioned.

    Lags are `len(u) // (4 max_order)` samples apart, so the order describes the record, not
    the sampling rate.

    A constant input has order 1 (it excites the static gain only); a sinusoid 2; an n-th order
    linear system needs an input of order 2n to be identified from steady excitation (seed 003).

    Parameters
    ----------
    u : numpy.ndarray
        The input series, shape (N,).
    max_order : int, optional
        Largest order examined.

    Returns
    -------
    int
        The order, 0 to `max_order`: 0 for an all-zero input, 1 for a record shorter than
        2·`max_order` samples; an order counts when the smallest eigenvalue of its block exceeds
        `PE_RATIO` times the largest.
    """
    n = u.size
    if n < 2 * max_order or not np.any(u):
        return 0 if not np.any(u) else 1
    # lags spaced over a quarter of the record: at fine sampling, neighbouring samples of any
    # smooth input are nearly equal, which would make every slow input look "constant"
    spacing = max(1, n // (4 * max_order))
    rows = n - (max_order - 1) * spacing
    lagged = np.column_stack([u[(max_order - 1 - k) * spacing:][:rows] for k in range(max_order)])
    full = lagged.T @ lagged / rows   # positive semidefinite by construction, as its leading blocks
    # the leading m×m blocks in one batched call: each padded with its own mean eigenvalue
    # (trace/m), which lies between its extremes and so changes neither
    inside, beyond = _leading_blocks(max_order)
    stack = np.where(inside, full, 0.0)
    diagonal = np.arange(max_order)
    mean_eig = np.cumsum(np.diag(full)) / (diagonal + 1)
    stack[:, diagonal, diagonal] += np.where(beyond, mean_eig[:, None], 0.0)
    eig = np.linalg.eigvalsh(stack)
    conditioned = eig[:, 0] > PE_RATIO * eig[:, -1]
    return int(max_order if conditioned.all() else np.argmin(conditioned))


@functools.lru_cache(maxsize=8)
def _leading_blocks(size: int) -> tuple[np.ndarray, np.ndarray]:
    """(inside, beyond): inside[m-1] masks the leading m×m block of a size×size matrix, beyond[m-1]
    the diagonal entries after it."""
    k = np.arange(size)
    order = k + 1
    inside = (k[None, :, None] < order[:, None, None]) & (k[None, None, :] < order[:, None, None])
    return inside, k[None, :] >= order[:, None]


def input_warnings(inputs: dict[str, list[np.ndarray]], interpolation: str,
                   coupled: dict[str, list[str]] | None = None) -> list[FitWarning]:
    """Constant inputs (order-1 excitation) and inputs rougher than the sampling resolves.

    `coupled` names, per input, the free parameters that act on it (∂²f/∂u∂p ≠ 0): those an
    input of low order leaves poorly determined.

    Parameters
    ----------
    inputs : dict of str to list of numpy.ndarray
        Per input name, its series in each experiment.
    interpolation : str
        The input interpolation of the fit; roughness is reported only under ``"foh"``.
    coupled : dict of str to list of str or None, optional
        Per input, the free parameters acting on it.

    Returns
    -------
    list of FitWarning
        ``input_not_exciting`` for an input of persistent excitation order ≤ 1 in every experiment,
        ``input_faster_than_sampling`` for an input whose effective ω·Δt exceeds `ROUGH_INPUT`.
    """
    out = []
    for name, series in inputs.items():
        orders = [persistent_excitation_order(u) for u in series]
        if max(orders, default=0) <= 1:
            params = (coupled or {}).get(name, [])
            out.append(FitWarning(
                code="input_not_exciting",
                message=f"input '{name}' has persistent excitation of order {max(orders, default=0)} "
                        "(constant, or one step early in the record): it reveals static gains, "
                        "hardly time constants" + (f"; poorly determined: {', '.join(params)}" if params
                                                   else "")
                        + "; add steps and sinusoids of several frequencies",
                detail={"input": name, "pe_order": orders, "parameters": params}))
        rough = max((_roughness(u) for u in series), default=0.0)
        if interpolation == "foh" and rough > ROUGH_INPUT:
            out.append(FitWarning(
                code="input_faster_than_sampling",
                message=f"input '{name}' changes between samples as fast as the sampling can show "
                        f"(effective ω·Δt ≈ {rough:.2f}); linear interpolation misrepresents it and "
                        "biases output error: give the input on a finer time grid (outputs null "
                        "where not measured) or use input_interpolation 'zoh' if it is held",
                detail={"input": name, "omega_dt": rough}))
    return out


def _roughness(u: np.ndarray) -> float:
    """Effective ω·Δt from rms(Δ²u)/rms(u - mean): (ωΔt)² for a sinusoid well sampled."""
    centred = u - u.mean()
    spread = float(np.sqrt(np.mean(centred ** 2)))
    if u.size < 3 or spread == 0:
        return 0.0
    ratio = float(np.sqrt(np.mean(np.diff(u, 2) ** 2))) / spread
    return float(np.sqrt(min(ratio, 4.0)))


def step_size_warning(max_rate: float, dt: float, substeps: int, integrator: str) -> list[FitWarning]:
    """RK4 with |λ|·h above ~0.5 per step is inaccurate on the model's fastest mode.

    Parameters
    ----------
    max_rate : float
        |λ| of the model's fastest mode, in 1/s.
    dt : float
        Sample step, in s.
    substeps : int
        Integrator steps per sample.
    integrator : str
        Name of the integrator; only fixed-step ones are checked.

    Returns
    -------
    list of FitWarning
        One ``integration_step_coarse`` warning with the substeps that bring |λ|h to 0.25, or none.
    """
    if not INTEGRATORS[integrator].fixed_step or not np.isfinite(max_rate):
        return []
    h = dt / substeps
    if max_rate * h <= 0.5:
        return []
    need = int(np.ceil(max_rate * dt / 0.25))
    return [FitWarning(
        code="integration_step_coarse",
        message=f"the model's fastest mode (|λ| ≈ {max_rate:.3g} 1/s) is coarse for RK4 at "
                f"h = {h:.3g} s (|λ|h = {max_rate * h:.2f}); raise options.substeps to about {need}",
        detail={"max_rate": max_rate, "step": h, "suggested_substeps": need})]
