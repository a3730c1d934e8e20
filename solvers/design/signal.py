"""The designed input as decision variables: levels held on the hold grid, or a multisine's coefficients.

Both map a vector z to the full input matrix U (inputs × samples), held inputs included, with bounds on
z and linear constraints g(z) (amplitude where z does not bound it, rate of change), so that the
design's NLP is the same whatever the signal.
"""
from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from greyfit.schemas.design import DesignRequest


@dataclass
class Signal:
    """z -> U, with the NLP's bounds and constraints.

    basis : (pieces × samples) matrix mapping one free input's coefficients to its samples.
    """

    free: list[int]            # rows of the free inputs in U
    fixed: np.ndarray          # U's value on the held inputs' rows (0 on the free rows)
    basis: np.ndarray
    lbz: np.ndarray
    ubz: np.ndarray
    lower: np.ndarray          # per free input
    upper: np.ndarray
    rate: np.ndarray           # per free input: the largest change between two samples (inf: none)
    amplitude_in_g: bool       # multisine: the samples' bounds are constraints, not z's bounds
    kind: str

    @property
    def nz(self) -> int:
        """Number of decision variables.

        Returns
        -------
        int
            Number of decision variables.
        """
        return len(self.free) * self.basis.shape[0]

    def inputs(self, z):
        """U (inputs × samples) of z, symbolic or numeric.

        Parameters
        ----------
        z : numpy.ndarray or casadi.MX
            The decision variables.

        Returns
        -------
        numpy.ndarray or casadi.MX
            Inputs × samples.
        """
        nf, m = len(self.free), self.basis.shape[0]
        numeric = isinstance(z, np.ndarray)
        Z = np.reshape(z, (nf, m)) if numeric else ca.reshape(z, m, nf).T
        free_rows = Z @ self.basis
        if numeric:
            U = self.fixed.copy()
            U[self.free, :] += free_rows
            return U
        place = np.zeros((self.fixed.shape[0], nf))
        place[self.free, range(nf)] = 1.0
        return ca.DM(self.fixed) + ca.DM(place) @ free_rows

    def constraints(self, z) -> tuple[ca.MX, np.ndarray, np.ndarray]:
        """g(z), lbg, ubg: sample bounds (multisine) and rates of change.

        Parameters
        ----------
        z : casadi.MX
            The decision variables.

        Returns
        -------
        tuple of (casadi.MX, numpy.ndarray, numpy.ndarray)
            g(z) and its lower and upper bounds.
        """
        U = self.inputs(z)
        rows, lb, ub = [], [], []
        for i, r in enumerate(self.free):
            if self.amplitude_in_g:
                rows.append(U[r, :].T)
                n = U.shape[1]
                lb.append(np.full(n, self.lower[i]))
                ub.append(np.full(n, self.upper[i]))
            if np.isfinite(self.rate[i]):
                d = (U[r, 1:] - U[r, :-1]).T
                rows.append(d)
                lb.append(np.full(d.shape[0], -self.rate[i]))
                ub.append(np.full(d.shape[0], self.rate[i]))
        if not rows:
            return ca.MX(0, 1), np.zeros(0), np.zeros(0)
        return ca.vertcat(*rows), np.concatenate(lb), np.concatenate(ub)

    def start(self, rng: np.random.Generator) -> np.ndarray:
        """A seeded starting z inside the bounds.

        Parameters
        ----------
        rng : numpy.random.Generator
            Seeded.

        Returns
        -------
        numpy.ndarray
            A starting z.
        """
        m = self.basis.shape[0]
        Z = np.empty((m, len(self.free)))
        for i in range(len(self.free)):
            lo, hi = self.lower[i], self.upper[i]
            if self.kind == "piecewise_constant":
                Z[:, i] = _rate_limited_levels(rng, m, lo, hi, self.rate[i])
            else:
                k = (m - 1) // 2
                Z[0, i] = 0.5 * (lo + hi)
                Z[1:, i] = rng.uniform(-1, 1, m - 1) * (hi - lo) / (4 * max(k, 1))
        return Z.T.reshape(-1)

    def project(self, U: np.ndarray) -> np.ndarray:
        """The z whose signal is closest to the free rows of U (least squares), clipped to z's bounds.

        Parameters
        ----------
        U : numpy.ndarray
            Inputs × samples.

        Returns
        -------
        numpy.ndarray
            The z closest to U.
        """
        Z, *_ = np.linalg.lstsq(self.basis.T, U[self.free, :].T, rcond=None)
        return np.clip(Z.T.reshape(-1), self.lbz, self.ubz)


def _rate_limited_levels(rng: np.random.Generator, m: int, lo: float, hi: float, rate: float) -> np.ndarray:
    levels = rng.uniform(lo, hi, m)
    if np.isfinite(rate):
        for j in range(1, m):
            levels[j] = np.clip(levels[j], levels[j - 1] - rate, levels[j - 1] + rate)
    return levels


def design_grid(request: DesignRequest) -> np.ndarray:
    """The sample times 0, Ts, 2Ts, ... up to the duration.

    Parameters
    ----------
    request : DesignRequest
        Its duration and sample time.

    Returns
    -------
    numpy.ndarray
        The sample times.
    """
    n = int(np.floor(request.duration / request.sample_time + 1e-9)) + 1
    return np.round(np.arange(n) * request.sample_time, 12)   # 0.3, not 0.30000000000000004


def make_signal(request: DesignRequest, inputs: list[str], time: np.ndarray) -> Signal:
    """The signal the request asks for, on the given sample times.

    Parameters
    ----------
    request : DesignRequest
        Its `inputs` limits, `hold`, `signal` and `frequencies`.
    inputs : list of str
        The model's inputs in order.
    time : ndarray
        Sample times.

    Returns
    -------
    Signal
    """
    free = [i for i, name in enumerate(inputs) if request.inputs[name].free]
    n = len(time)
    fixed = np.zeros((len(inputs), n))
    for i, name in enumerate(inputs):
        if not request.inputs[name].free:
            fixed[i, :] = request.inputs[name].value
    lim = [request.inputs[inputs[i]] for i in free]
    lower = np.array([float(x.lower) for x in lim])   # type: ignore[arg-type]
    upper = np.array([float(x.upper) for x in lim])   # type: ignore[arg-type]
    if request.signal == "multisine":
        basis, rate_step = _multisine_basis(request, time), request.sample_time
    else:
        basis, rate_step = _hold_basis(request, n), request.hold or request.sample_time
    rate = np.array([x.max_rate * rate_step if x.max_rate else np.inf for x in lim])
    m = basis.shape[0]
    if request.signal == "multisine":
        span = upper - lower
        lbz = np.concatenate([np.concatenate([[lower[i]], np.full(m - 1, -span[i])]) for i in range(len(free))])
        ubz = np.concatenate([np.concatenate([[upper[i]], np.full(m - 1, span[i])]) for i in range(len(free))])
    else:
        lbz, ubz = np.repeat(lower, m), np.repeat(upper, m)
    # z is ordered piece-major within an input: input i's coefficients are z[i*m:(i+1)*m]
    return Signal(free, fixed, basis, lbz, ubz, lower, upper, rate, request.signal == "multisine", request.signal)


def _hold_basis(request: DesignRequest, n: int) -> np.ndarray:
    per = int(round((request.hold or request.sample_time) / request.sample_time))
    pieces = -(-n // per)
    basis = np.zeros((pieces, n))
    basis[np.arange(n) // per, np.arange(n)] = 1.0
    return basis


def default_frequencies(request: DesignRequest) -> np.ndarray:
    """Eight frequencies log-spaced from 1/duration to a fifth of the sampling rate (Hz).

    Parameters
    ----------
    request : DesignRequest
        Its duration and sample time.

    Returns
    -------
    numpy.ndarray
        Frequencies in Hz.
    """
    return np.geomspace(1.0 / request.duration, 0.2 / request.sample_time, 8)


def _multisine_basis(request: DesignRequest, time: np.ndarray) -> np.ndarray:
    f = np.asarray(request.frequencies if request.frequencies else default_frequencies(request), dtype=float)
    arg = 2 * np.pi * np.outer(f, time)
    return np.vstack([np.ones_like(time), np.sin(arg), np.cos(arg)])
