"""T-optimal inputs: the signal under which no rival can imitate the model's outputs (nor the model a rival's).

For every ordered pair (truth, rival) the divergence is Σ((y_truth − y_rival(θ))/σ)² with the rival's
free parameters θ refitted to the truth's noise-free outputs: the expected rise of the rival's χ² if
the truth made the data. The design maximises the smallest divergence over the pairs, in rounds of
Atkinson and Fedorov's alternation: refit every rival on the current input, then redesign the input
with those fits held (an epigraph NLP: maximise s subject to s ≤ each pair's divergence), until the
rounds run out; the input with the largest refitted divergence is kept.
"""
from __future__ import annotations

from dataclasses import dataclass

import casadi as ca
import numpy as np

from greyfit.schemas.design import DesignRequest
from greyfit.solvers.design.setup import Candidate, DesignSetup, candidate
from greyfit.solvers.design.simulation import trajectory_function
from greyfit.solvers.errors import DataError

_IPOPT = {"ipopt.print_level": 0, "print_time": False, "ipopt.sb": "yes"}


@dataclass
class Pair:
    """A comparison: `truth` makes the data, `rival` (its free parameters refitted) imitates it."""

    truth: Candidate
    rival: Candidate


@dataclass
class PairFit:
    """A rival's best imitation of the truth on one input."""

    divergence: float
    rival_p: np.ndarray


def rival_pairs(setup: DesignSetup, request: DesignRequest) -> list[Pair]:
    """Both directions of the model against each rival.

    Parameters
    ----------
    setup : DesignSetup
        The laid-out design (the model).
    request : DesignRequest
        Its rivals and outputs.

    Returns
    -------
    list of Pair
        (model, rival) and (rival, model) for each rival.
    """
    main = setup.model
    pairs = []
    for k, rival in enumerate(request.rivals):
        other = candidate(rival.model, {}, request.outputs, f"rivals[{k}].model")
        other.name = rival.name
        if sorted(other.cm.inputs) != sorted(main.cm.inputs):
            raise DataError(f"the rival's inputs ({', '.join(other.cm.inputs)}) differ from the model's "
                            f"({', '.join(main.cm.inputs)})", f"rivals[{k}].model.inputs")
        if sorted(other.cm.states) != sorted(main.cm.states) and request.initial_state:
            missing = [s for s in request.initial_state if s not in other.cm.states]
            if missing:
                raise DataError(f"initial_state names {missing[0]!r}, which the rival does not have",
                                f"rivals[{k}].model.states")
        pairs += [Pair(main, other), Pair(other, main)]
    return pairs


def _inputs_for(cand: Candidate, main: Candidate, U):
    """U's rows reordered to `cand`'s input order (U is in the main model's)."""
    order = [main.cm.inputs.index(name) for name in cand.cm.inputs]
    return U[order, :]


def _x0(cand: Candidate, request: DesignRequest) -> np.ndarray:
    return np.array([request.initial_state.get(name, 0.0) for name in cand.cm.states], dtype=float)


def _outputs(cand: Candidate, main: Candidate, U, p, time: np.ndarray, request: DesignRequest, x0=None):
    n = len(time)
    fun = trajectory_function(cand.cm, n, request.options.substeps, cand.measured.rows)
    return fun(_x0(cand, request) if x0 is None else x0, _inputs_for(cand, main, U), p,
               time.reshape(1, -1), np.diff(time).reshape(1, -1))


def _weighted_gap(pair: Pair, main: Candidate, U, p_rival, time, request: DesignRequest):
    yt = _outputs(pair.truth, main, U, pair.truth.p, time, request)
    yr = _outputs(pair.rival, main, U, p_rival, time, request)
    return (yt - yr) / ca.DM(pair.truth.measured.sigma)


def refit_rival(pair: Pair, main: Candidate, U: np.ndarray, time: np.ndarray, request: DesignRequest,
                start: np.ndarray) -> PairFit:
    """The rival's free parameters that imitate the truth's outputs best on input U (Ipopt, bounded).

    Parameters
    ----------
    pair : Pair
        The comparison.
    main : Candidate
        The model whose input order U has.
    U : ndarray
        Inputs × samples.
    time : ndarray
        Sample times.
    request : DesignRequest
        Options.
    start : ndarray
        The rival's full parameter vector to start from.

    Returns
    -------
    PairFit
    """
    rival = pair.rival
    free = list(rival.free)
    scale = np.where(np.abs(start[free]) > 0, np.abs(start[free]), 1.0)
    theta = ca.MX.sym("theta", len(free))
    p = ca.MX(ca.DM(start))
    for j, i in enumerate(free):
        p[i] = theta[j] * scale[j]
    gap = _weighted_gap(pair, main, ca.DM(U), p, time, request)
    f = ca.sumsqr(gap)
    solver = ca.nlpsol("imitate", "ipopt", {"x": theta, "f": f}, {**_IPOPT, "ipopt.max_iter": 200})
    best = None
    for p0 in (start, rival.p):
        sol = solver(x0=p0[free] / scale, lbx=rival.lower / scale, ubx=rival.upper / scale)
        value = float(sol["f"])
        if best is None or value < best.divergence:
            full = start.copy()
            full[free] = np.asarray(sol["x"], dtype=float).reshape(-1) * scale
            best = PairFit(value, full)
    assert best is not None
    return best


def _redesign(setup: DesignSetup, request: DesignRequest, pairs: list[Pair], fits: list[PairFit],
              z0: np.ndarray) -> tuple[np.ndarray, str, int]:
    """Maximise the smallest divergence with the rivals' parameters held at `fits`."""
    signal, main = setup.signal, setup.model
    z, s = ca.MX.sym("z", signal.nz), ca.MX.sym("s")
    U = signal.inputs(z)
    scale = max(min(f.divergence for f in fits), 1e-6)
    gaps = [ca.sumsqr(_weighted_gap(pair, main, U, ca.DM(fit.rival_p), setup.time, request)) / scale - s
            for pair, fit in zip(pairs, fits)]
    g0, lbg0, ubg0 = signal.constraints(z)
    g = ca.vertcat(g0, *gaps)
    lbg = np.concatenate([lbg0, np.zeros(len(gaps))])
    ubg = np.concatenate([ubg0, np.full(len(gaps), np.inf)])
    solver = ca.nlpsol("discriminate", "ipopt", {"x": ca.vertcat(z, s), "f": -s, "g": g},
                       {**_IPOPT, "ipopt.max_iter": request.options.max_iterations,
                        "ipopt.hessian_approximation": "limited-memory"})
    sol = solver(x0=np.concatenate([z0, [1.0]]), lbx=np.concatenate([signal.lbz, [0.0]]),
                 ubx=np.concatenate([signal.ubz, [np.inf]]), lbg=lbg, ubg=ubg)
    stats = solver.stats()
    z_new = np.clip(np.asarray(sol["x"], dtype=float).reshape(-1)[:-1], signal.lbz, signal.ubz)
    return z_new, str(stats.get("return_status", "")), int(stats.get("iter_count", 0))


@dataclass
class Discriminated:
    """The kept design and its refitted pairs."""

    z: np.ndarray
    fits: list[PairFit]
    status: str
    iterations: int

    @property
    def smallest(self) -> float:
        """The smallest divergence over the pairs.

        Returns
        -------
        float
            The smallest divergence over the pairs.
        """
        return min(f.divergence for f in self.fits)


def fit_pairs(pairs: list[Pair], main: Candidate, U: np.ndarray, time: np.ndarray, request: DesignRequest,
              starts: list[np.ndarray] | None = None) -> list[PairFit]:
    """Every rival refitted to its truth on input U.

    Parameters
    ----------
    pairs : list of Pair
        The comparisons.
    main : Candidate
        The model whose input order U has.
    U : numpy.ndarray
        Inputs × samples.
    time : numpy.ndarray
        Sample times.
    request : DesignRequest
        Options.
    starts : list of numpy.ndarray, optional
        Each rival's parameters to start from (default its own).

    Returns
    -------
    list of PairFit
        One per pair.
    """
    return [refit_rival(pair, main, U, time, request, pair.rival.p if starts is None else starts[k])
            for k, pair in enumerate(pairs)]


def solve_discrimination_design(setup: DesignSetup, request: DesignRequest, starts: list[np.ndarray],
                                pairs: list[Pair]) -> Discriminated:
    """Rounds of refit and redesign from each start; the input whose refitted smallest divergence is largest.

    Parameters
    ----------
    setup : DesignSetup
        The laid-out design.
    request : DesignRequest
        Rivals, options.
    starts : list of ndarray
        Starting z's.
    pairs : list of Pair
        From `rival_pairs`.

    Returns
    -------
    Discriminated
    """
    best = None
    for z in starts:
        fits = fit_pairs(pairs, setup.model, setup.signal.inputs(z), setup.time, request)
        status, iterations = "", 0
        for _ in range(request.options.rounds):
            z_new, status_new, it = _redesign(setup, request, pairs, fits, z)
            fits_new = fit_pairs(pairs, setup.model, setup.signal.inputs(z_new), setup.time, request,
                                 [f.rival_p for f in fits])
            iterations += it
            if min(f.divergence for f in fits_new) <= min(f.divergence for f in fits):
                break   # the refitted rivals caught up: this start has converged
            z, fits, status = z_new, fits_new, status_new
        candidate_design = Discriminated(z, fits, status or "Start_Kept", iterations)
        if best is None or candidate_design.smallest > best.smallest:
            best = candidate_design
    assert best is not None
    return best
