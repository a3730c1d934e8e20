"""What the learned disturbance depends on: d̂ against each state, input and simple combination.

For each variable z a smooth function g(z) (a cubic regression spline with knots at quantiles of z)
is fitted to d̂ together with terms linear in every state and input (those the declared parameters
can take up when the model is refitted: a damping absorbed a friction, a stiffness a cubic spring).
The share of d̂'s variance explained ranks the variables; every variable gets the same number of
basis functions, so the shares are comparable. `shape_agreement` scores a candidate law the same way.
The best variable's law is also evaluated on a grid of that variable alone (`law_grid`, `law_values`):
the fitted values at the samples hold the linear terms in the other states too, and drawn against the
variable they zigzag.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

KNOTS = 6                  # interior knots of the spline
MAX_PUBLIC_SAMPLES = 1000  # series in the result are thinned to this many samples per experiment
TOP_ALTERNATIVES = 5
LAW_POINTS = 200           # points of the law on its variable's grid


@dataclass
class ShapeEstimate:
    """One channel's estimate at full resolution, per experiment (the public form is thinned)."""

    equation: str
    d: list[np.ndarray]                     # d̂ per experiment (n,)
    time: list[np.ndarray]
    variables: dict[str, list[np.ndarray]]  # name -> per experiment (n,)
    linear: list[np.ndarray]                # per experiment (n, k): states and inputs, for the linear terms
    log_likelihood: float = -np.inf
    q: float = 0.0
    residual_share: float = 0.0
    variable: str | None = None
    share_explained: float | None = None
    law: list[np.ndarray] = field(default_factory=list)
    alternatives: dict[str, float] = field(default_factory=dict)
    linear_names: list[str] = field(default_factory=list)   # the columns of `linear` (states, then inputs)
    law_grid: np.ndarray = field(default_factory=lambda: np.zeros(0))     # `variable` from its min to its max
    law_values: np.ndarray = field(default_factory=lambda: np.zeros(0))   # the law at `law_grid`
    # per experiment (n, k) columns -> what the smoother would estimate were each the disturbance
    imprint: Optional[Callable[[list[np.ndarray]], list[np.ndarray]]] = None


def candidate_variables(state_names, states, input_names, inputs) -> dict[str, list[np.ndarray]]:
    """States, inputs, products of two of them and differences of a state and an input.

    Parameters
    ----------
    state_names : list of str
        The states' names.
    states : list of numpy.ndarray
        (nx, n) states per experiment.
    input_names : list of str
        The inputs' names.
    inputs : list of numpy.ndarray
        (nu, n) inputs per experiment.

    Returns
    -------
    dict of str to list of numpy.ndarray
        Name ("x", "u", "x*u", "x-u") -> its (n,) samples per experiment.
    """
    base = {n: [x[i] for x in states] for i, n in enumerate(state_names)}
    ins = {n: [u[j] for u in inputs] for j, n in enumerate(input_names)}
    out = {**base, **ins}
    names = list(out)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            out[f"{a}*{b}"] = [p * q for p, q in zip(out[a], out[b])]
    for a in base:
        for b in ins:
            out[f"{a}-{b}"] = [p - q for p, q in zip(base[a], ins[b])]
    return out


def spline_basis(z: np.ndarray, reference: np.ndarray | None = None) -> np.ndarray:
    """[z, z², z³, (z - κ)³₊ …] on z standardised, knots at quantiles (a natural choice for any law).

    Parameters
    ----------
    z : numpy.ndarray
        (n,) values of the variable to evaluate the basis at.
    reference : numpy.ndarray or None
        The samples whose mean, spread and quantiles define the basis; None: `z` itself. Give the
        samples the law was fitted on to evaluate it elsewhere (on a grid).

    Returns
    -------
    numpy.ndarray
        (n, 3 + KNOTS) basis columns.
    """
    ref = z if reference is None else reference
    s = np.std(ref)
    zs = (z - np.mean(ref)) / (s if s > 0 else 1.0)
    knots = np.quantile((ref - np.mean(ref)) / (s if s > 0 else 1.0), np.linspace(0, 1, KNOTS + 2)[1:-1])
    cols = [zs, zs ** 2, zs ** 3] + [np.clip(zs - k, 0, None) ** 3 for k in knots]
    return np.column_stack(cols)


def explained_share(d: np.ndarray, columns: np.ndarray) -> tuple[float, np.ndarray]:
    """(R² of d on [1, columns], fitted values) by least squares.

    Parameters
    ----------
    d : numpy.ndarray
        (n,) the series to explain.
    columns : numpy.ndarray
        (n, k) regressors (a constant is added).

    Returns
    -------
    tuple of (float, numpy.ndarray)
        R² (0 when d is constant) and the (n,) fitted values.
    """
    _, fit = least_squares(d, columns)
    sst = float(np.sum((d - d.mean()) ** 2))
    return (1.0 - float(np.sum((d - fit) ** 2)) / sst if sst > 0 else 0.0), fit


def least_squares(d: np.ndarray, columns: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(coefficients of [1, columns], fitted values) of d by least squares.

    Parameters
    ----------
    d : numpy.ndarray
        (n,) the series to explain.
    columns : numpy.ndarray
        (n, k) regressors (a constant is added as the first column).

    Returns
    -------
    tuple of (numpy.ndarray, numpy.ndarray)
        The (k + 1,) coefficients, in the units of the columns as given (the constant's first), and
        the (n,) fitted values.
    """
    a = np.column_stack([np.ones(d.size), columns])
    scale = np.maximum(np.abs(a).max(axis=0), 1e-300)
    a = a / scale
    # normal equations with a whisper of ridge: a few columns, thousands of rows, many variables to
    # try (an SVD per variable cost 0.1 s here); the ridge only guards collinear columns
    gram = a.T @ a
    gram[np.diag_indices_from(gram)] += 1e-10 * np.trace(gram) / gram.shape[0]
    coef = np.linalg.solve(gram, a.T @ d)
    return coef / scale, a @ coef


def law_on_grid(est: ShapeEstimate, name: str, points: int = LAW_POINTS) -> tuple[np.ndarray, np.ndarray]:
    """The smooth law of one variable fitted to d̂, as a function of that variable alone.

    d̂ is fitted (as in `relate`) by a constant, the spline in z and terms linear in the states and
    inputs. On a grid of z the law is the constant plus the spline plus, where z is itself one of the
    states or inputs, its linear term; the other linear terms are held at their means, so the curve
    runs through the middle of d̂ plotted against z.

    Parameters
    ----------
    est : ShapeEstimate
        One channel's estimate (its `linear_names` name the columns of `linear`).
    name : str
        The variable (a key of `est.variables`).
    points : int
        Grid points, evenly spaced from the variable's smallest sample to its largest.

    Returns
    -------
    tuple of (numpy.ndarray, numpy.ndarray)
        (grid, law at the grid), each (points,).
    """
    z, d = np.concatenate(est.variables[name]), np.concatenate(est.d)
    linear = np.concatenate(est.linear)
    basis = spline_basis(z)
    coef, _ = least_squares(d, np.column_stack([basis, linear]))
    grid = np.linspace(z.min(), z.max(), points)
    held = np.tile(linear.mean(axis=0), (points, 1))
    if name in est.linear_names:
        held[:, est.linear_names.index(name)] = grid
    k = basis.shape[1]
    return grid, coef[0] + spline_basis(grid, reference=z) @ coef[1:1 + k] + held @ coef[1 + k:]


def relate(est: ShapeEstimate) -> None:
    """Fill `variable`, `share_explained`, `law`, `law_grid`, `law_values` and `alternatives` of an estimate.

    Left unchanged when d̂ has too few samples, is not finite or is constant, or no variable can be used.

    Parameters
    ----------
    est : ShapeEstimate
        One channel's estimate; changed in place.

    Returns
    -------
    None
    """
    d = np.concatenate(est.d)
    if d.size < 3 * (KNOTS + 4) or not np.all(np.isfinite(d)) or np.std(d) == 0:
        return
    linear = np.concatenate(est.linear)
    shares: dict[str, tuple[float, np.ndarray]] = {}
    for name, series in est.variables.items():
        z = np.concatenate(series)
        if not np.all(np.isfinite(z)) or np.std(z) == 0:
            continue
        share, fit = explained_share(d, np.column_stack([spline_basis(z), linear]))
        if np.isfinite(share) and np.all(np.isfinite(fit)):
            shares[name] = (share, fit)
    if not shares:
        return
    ranked = sorted(shares, key=lambda k: shares[k][0], reverse=True)
    best = ranked[0]
    est.variable, est.share_explained = best, float(max(shares[best][0], 0.0))
    est.law = np.split(shares[best][1], np.cumsum([x.size for x in est.d])[:-1])
    est.law_grid, est.law_values = law_on_grid(est, best)
    est.alternatives = {k: round(float(shares[k][0]), 4) for k in ranked[1:1 + TOP_ALTERNATIVES]}


def shape_agreement(estimate: ShapeEstimate, candidate: list[np.ndarray] | np.ndarray) -> float:
    """How much of the learned shape a candidate law explains, for scoring laws against the shape.

    Parameters
    ----------
    estimate : ShapeEstimate
        One channel's disturbance (`estimate_shape(...).estimates[i]`), at full resolution.
    candidate : list of arrays, or array
        The candidate term g(t) (without its coefficient) evaluated at the samples of each
        experiment, on the same trajectory (`estimate.variables` holds the smoothed states and the
        inputs to evaluate it on); one array when there is one experiment.

    Returns
    -------
    float
        The share of d̂'s variance explained by β·g plus terms linear in the states and inputs (which
        the declared parameters take up when refitted), in [0, 1]; compare it with
        `estimate.share_explained`, what a free smooth function of the best single variable explains:
        a law far below it does not have the shape of the missing term (it approximates, at best).
        0 when g is constant or not finite.
    """
    terms = [np.ravel(c) for c in (candidate if isinstance(candidate, list) else [candidate])]
    g = np.concatenate(terms)
    d = np.concatenate(estimate.d)
    if g.size != d.size or not np.all(np.isfinite(g)) or np.std(g) == 0:
        return 0.0
    per_exp = [np.column_stack([t, lin]) for t, lin in zip(terms, estimate.linear)]
    if estimate.imprint is not None and len(per_exp) == len(estimate.d) and \
            all(c.shape[0] == e.size for c, e in zip(per_exp, estimate.d)):
        # the law and the linear terms as the smoother would have seen them (see `shape_kalman.imprint`)
        per_exp = estimate.imprint(per_exp)
    share, _ = explained_share(d, np.vstack(per_exp))
    return float(min(max(share, 0.0), 1.0))


def public_samples(series: list[np.ndarray], stride: int) -> list[list[float]]:
    """Every `stride`-th sample of each series, as plain floats for the result.

    Parameters
    ----------
    series : list of numpy.ndarray
        One series per experiment.
    stride : int
        Keep every stride-th sample (`thinning`).

    Returns
    -------
    list of list of float
        The thinned series.
    """
    return [[float(v) for v in np.asarray(s)[::stride]] for s in series]


def thinning(n_max: int) -> int:
    """The stride that brings `n_max` samples down to at most `MAX_PUBLIC_SAMPLES`.

    Parameters
    ----------
    n_max : int
        The longest experiment's number of samples.

    Returns
    -------
    int
        The stride, ≥ 1.
    """
    return max(1, int(np.ceil(n_max / MAX_PUBLIC_SAMPLES)))
