"""The shape step's smoother: a random-walk disturbance on one equation, estimated by a Kalman
filter and smoother on the model linearised along a trajectory.

State z = [δx; d] (m = nx + 1): δx the departure of the states from the trajectory, d a
disturbance held over each sample interval and added to one state equation (or to one output).
    δx_{k+1} = A_k δx_k + b_k d_k + c_k,   d_{k+1} = d_k + w_k,   w_k ~ N(0, q σ²)
    r_k = H_k δx_k + h_d d_k + e_k,        e_k ~ N(0, σ² I)   (weighted output residual)
`c_k` is the linearisation's gap (zero along an exact simulation): with it, smoothing around the
last estimate is one Gauss-Newton step of the MAP problem, the iterated extended smoother.
σ² is concentrated out (every covariance is in units of σ²), so the likelihood of q is exact for
the linear model. Outputs are processed one at a time (univariate filtering, Koopman & Durbin),
so no matrix is inverted; the smoother is the backward recursion of de Jong (r_{k-1} = Hᵀv/F + Lᵀr),
which needs no inverse either. Both run as CasADi `mapaccum` loops: a few ms for 4 000 samples.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import casadi as ca
import numpy as np


@dataclass
class Linearised:
    """Per-sample matrices of one experiment, column-major vectors stacked as columns (…, n)."""

    a: np.ndarray        # (nx*nx, n) vec(A_k); the last column unused
    b: np.ndarray        # (nx, n) the disturbance's column of ∂x+/∂d
    c: np.ndarray        # (m, n) gap of the linearisation (zero along a simulation)
    h: np.ndarray        # (ny*nx, n) vec(H_k)
    hd: np.ndarray       # (ny,) the disturbance's coefficient in each output (output channel only)
    r: np.ndarray        # (ny, n) weighted output residual, 0 where missing
    mask: np.ndarray     # (ny, n) 1 where measured
    p0: np.ndarray       # (m,) diagonal of the (diffuse) prior covariance of z_0, in σ² units

    @property
    def n(self) -> int:
        """Number of samples of the experiment.

        Returns
        -------
        int
            Columns of `r`.
        """
        return self.r.shape[1]


# CasADi's interpreter, not compiled C: generated C called through mapaccum measured 3× slower here
@lru_cache(maxsize=32)
def _forward(nx: int, ny: int, n: int) -> ca.Function:
    return _forward_step(nx, ny).mapaccum("kf", n, 2)


@lru_cache(maxsize=32)
def _backward(nx: int, ny: int, n: int) -> ca.Function:
    return _backward_step(nx, ny).mapaccum("ks", n, 1)


@lru_cache(maxsize=32)
def _forward_step(nx: int, ny: int) -> ca.Function:
    m = nx + 1
    a, pv = ca.SX.sym("a", m), ca.SX.sym("P", m * m)
    av, b, c = ca.SX.sym("A", nx * nx), ca.SX.sym("b", nx), ca.SX.sym("c", m)
    hv, hd, r, mask, q = ca.SX.sym("H", ny * nx), ca.SX.sym("hd", ny), ca.SX.sym("r", ny), ca.SX.sym("mask", ny), \
        ca.SX.sym("q")
    P = ca.reshape(pv, m, m)
    H = ca.reshape(hv, ny, nx)
    vs, fs, ks = [], [], []
    z = a
    for j in range(ny):
        hj = ca.vertcat(H[j, :].T, hd[j])
        ph = ca.mtimes(P, hj)
        f = ca.dot(hj, ph) + 1.0
        v = mask[j] * (r[j] - ca.dot(hj, z))
        k = mask[j] * ph / f
        z = z + k * v
        P = P - mask[j] * ca.mtimes(ph, ph.T) / f
        vs.append(v)
        fs.append(f)
        ks.append(k)
    T = ca.blockcat([[ca.reshape(av, nx, nx), b], [ca.DM.zeros(1, nx), ca.DM.ones(1, 1)]])
    z_next = ca.mtimes(T, z) + c
    P_next = ca.mtimes(ca.mtimes(T, P), T.T)
    P_next[m - 1, m - 1] += q
    P_next = 0.5 * (P_next + P_next.T)
    return ca.Function("greyfit_kf_step", [a, pv, av, b, c, hv, hd, r, mask, q],
                       [z_next, ca.vec(P_next), ca.vertcat(*vs), ca.vertcat(*fs), ca.vertcat(*ks)])


@lru_cache(maxsize=32)
def _backward_step(nx: int, ny: int) -> ca.Function:
    m = nx + 1
    rr = ca.SX.sym("r", m)
    av, b, hv, hd = ca.SX.sym("A", nx * nx), ca.SX.sym("b", nx), ca.SX.sym("H", ny * nx), ca.SX.sym("hd", ny)
    v, f, kv, mask = ca.SX.sym("v", ny), ca.SX.sym("F", ny), ca.SX.sym("K", m * ny), ca.SX.sym("mask", ny)
    T = ca.blockcat([[ca.reshape(av, nx, nx), b], [ca.DM.zeros(1, nx), ca.DM.ones(1, 1)]])
    H = ca.reshape(hv, ny, nx)
    K = ca.reshape(kv, m, ny)
    s = ca.mtimes(T.T, rr)
    for j in reversed(range(ny)):
        hj = ca.vertcat(H[j, :].T, hd[j])
        # L = I - K hᵀ; r ← h v/F + Lᵀ r
        s = mask[j] * hj * v[j] / f[j] + s - hj * ca.dot(K[:, j], s)
    return ca.Function("greyfit_ks_step", [rr, av, b, hv, hd, v, f, kv, mask], [s])



def _run_forward(lin: Linearised, q: float):
    nx = lin.b.shape[0]
    ny = lin.r.shape[0]
    m = nx + 1
    fwd = _forward(nx, ny, lin.n)
    z0 = np.zeros(m)
    p0 = np.diag(lin.p0).ravel(order="F")
    hd = np.repeat(lin.hd[:, None], lin.n, 1)
    zs, ps, v, f, k = fwd(z0, p0, lin.a, lin.b, lin.c, lin.h, hd, lin.r, lin.mask, np.full((1, lin.n), q))
    return z0, p0, np.array(zs), np.array(ps), np.array(v), np.array(f), np.array(k)


def log_likelihood(lins: list[Linearised], q: float) -> tuple[float, float]:
    """(concentrated log-likelihood, σ̂²) of the random-walk intensity q over all experiments.

    Parameters
    ----------
    lins : list of Linearised
        The linearised model of each experiment.
    q : float
        Random-walk intensity of the disturbance, in units of σ².

    Returns
    -------
    tuple of (float, float)
        The log-likelihood with σ² concentrated out (up to a constant), and σ̂², the measurement noise
        variance of the weighted output residual.
    """
    wss, logf, count = 0.0, 0.0, 0.0
    for lin in lins:
        *_, v, f, _ = _run_forward(lin, q)
        wss += float(np.sum(v ** 2 / f))
        logf += float(np.sum(lin.mask * np.log(f)))
        count += float(lin.mask.sum())
    sigma2 = max(wss / max(count, 1.0), 1e-300)
    return -0.5 * (count * np.log(sigma2) + logf), sigma2


def smooth(lin: Linearised, q: float) -> np.ndarray:
    """Smoothed z_k (m, n) = E[z_k | all data] for intensity q.

    Parameters
    ----------
    lin : Linearised
        The linearised model of one experiment.
    q : float
        Random-walk intensity of the disturbance, in units of σ².

    Returns
    -------
    numpy.ndarray
        (nx + 1, n) smoothed [δx; d] at every sample.
    """
    nx, ny, n = lin.b.shape[0], lin.r.shape[0], lin.n
    m = nx + 1
    z0, p0, zs, ps, v, f, k = _run_forward(lin, q)
    bwd = _backward(nx, ny, n)
    hd = np.repeat(lin.hd[:, None], n, 1)
    rev = np.s_[:, ::-1]
    rs = np.array(bwd(np.zeros(m), lin.a[rev], lin.b[rev], lin.h[rev], hd, v[rev], f[rev], k[rev],
                      lin.mask[rev]))[rev]          # rs[:, k] = r_{k,0}: after sample k's first update
    z_pred = np.hstack([z0[:, None], zs[:, :-1]])
    p_pred = np.hstack([p0[:, None], ps[:, :-1]]).reshape(m, m, n, order="F")
    return z_pred + np.einsum("ijk,jk->ik", p_pred, rs)


def best_intensity(lins: list[Linearised], grid=tuple(10.0 ** np.arange(-8, 5, 2))) -> tuple[float, float, float]:
    """(q, log-likelihood, σ̂²) maximising the likelihood: a grid every two decades, then one decade
    and half a decade either side of the best (the likelihood is smooth and unimodal in log q on
    every case measured).

    Parameters
    ----------
    lins : list of Linearised
        The linearised model of each experiment.
    grid : tuple of float
        The first grid of intensities (10⁻⁸ .. 10⁴ every two decades).

    Returns
    -------
    tuple of (float, float, float)
        The best q, its log-likelihood and σ̂².
    """
    scored = [(q, *log_likelihood(lins, q)) for q in grid]
    for step in (10.0, np.sqrt(10.0)):
        q0 = max(scored, key=lambda s: s[1])[0]
        scored += [(q, *log_likelihood(lins, q)) for q in (q0 / step, q0 * step)]
    return max(scored, key=lambda s: s[1])


def imprint(lins: list[Linearised], q: float, columns: list[np.ndarray]) -> list[np.ndarray]:
    """What the smoother would estimate if each column were the true disturbance: S·g.

    The smoother is linear in the residual, so a disturbance g (in the smoother's units) that makes
    the output residual r_g (δx_{k+1} = A_k δx_k + b_k g_k, r_g = H_k δx_k + h_d g_k, masked) is seen as
    S·g: smoothed in time as the learned disturbance itself is. A law is then compared with the learned
    disturbance on the same footing: a jump (sign(v) at each reversal) is spread over the samples
    around it in both, where a law compared raw would lose to any smooth curve.

    Parameters
    ----------
    lins : list of Linearised
        The linearisations the disturbance was estimated on, one per experiment.
    q : float
        The random-walk intensity it was estimated with.
    columns : list of numpy.ndarray
        Per experiment, (n, k): k disturbances in the smoother's units.

    Returns
    -------
    list of numpy.ndarray
        Per experiment, (n, k): each column's smoothed estimate.
    """
    out = []
    for lin, g in zip(lins, columns):
        nx, ny, n = lin.b.shape[0], lin.r.shape[0], lin.n
        g = np.asarray(g, dtype=float).reshape(n, -1)
        a = lin.a.reshape(nx, nx, n).transpose(1, 0, 2)     # A_k[row, col]: vec is column-major
        h = lin.h.reshape(nx, ny, n).transpose(1, 0, 2)
        dx = np.zeros((nx, g.shape[1]))
        resp = np.empty((ny, n, g.shape[1]))
        for k in range(n):
            resp[:, k] = h[:, :, k] @ dx + np.outer(lin.hd, g[k])
            dx = a[:, :, k] @ dx + np.outer(lin.b[:, k], g[k])
        smoothed = np.empty_like(g)
        zero = np.zeros_like(lin.c)
        for j in range(g.shape[1]):
            seen = Linearised(a=lin.a, b=lin.b, c=zero, h=lin.h, hd=lin.hd, r=lin.mask * resp[:, :, j],
                              mask=lin.mask, p0=lin.p0)
            smoothed[:, j] = smooth(seen, q)[nx]
        out.append(smoothed)
    return out
