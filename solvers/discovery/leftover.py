"""Say what is left: the final residual against the noise level, and the shape of what it holds.

The noise level is the shape step's estimate: the white measurement noise of the smoother's model
once the most likely disturbance is allowed for (maximum likelihood, `shape_kalman`). When the final
fit's RMS residual stays `UNEXPLAINED_RATIO` times above it on some output, the result says
`unexplained`, with the disturbance learned at the final fit and the share of the residual it holds.

Coloured measurement noise is not a missing term: when the most likely disturbance is on an output
path and no smooth function of the states and inputs explains it, the residual is as well explained
by a drifting sensor as by missing physics, and nothing is called unexplained (a note says so).
"""
from __future__ import annotations

import numpy as np

from greyfit.schemas.discovery import Unexplained
from greyfit.schemas.fit import FitResult
from greyfit.solvers.discovery.shape import ShapeResult

UNEXPLAINED_RATIO = 2.0     # final RMS residual over the noise level (white noise: 1.0 ± 0.05 measured)
COLOURED_NOISE_SHARE = 0.5  # an output-path shape explained less than this by the states: coloured noise


def looks_like_coloured_noise(shape: ShapeResult) -> bool:
    """Whether the most likely disturbance is on an output path and little of it is explained by the states.

    Parameters
    ----------
    shape : ShapeResult
        The shape step's estimates, most likely first.

    Returns
    -------
    bool
        True when the best estimate is on an output and explains less than `COLOURED_NOISE_SHARE`.
    """
    best = shape.estimates[0]
    return best.equation.startswith("output ") and (best.share_explained or 0.0) < COLOURED_NOISE_SHARE


def what_is_left(fit: FitResult, shape: ShapeResult) -> tuple[Unexplained | None, str]:
    """(`unexplained` or None, a note or "") for the final fit and the shape learned at it.

    Parameters
    ----------
    fit : FitResult
        The final fit (its RMSE per output).
    shape : ShapeResult
        The disturbance shape and noise level learned at that fit.

    Returns
    -------
    tuple of (Unexplained or None, str)
        An `Unexplained` report when some output's RMSE is above `UNEXPLAINED_RATIO` times its noise level
        and the leftover does not look like coloured noise; else None, with a note in the latter case.
    """
    ratios = {}
    for o, sigma in shape.noise_level.items():
        rmse = fit.metrics.rmse.get(o)
        if rmse is not None and sigma > 0 and np.isfinite(rmse):
            ratios[o] = float(rmse / sigma)
    above = [o for o, r in ratios.items() if r > UNEXPLAINED_RATIO]
    if not above:
        return None, ""
    if looks_like_coloured_noise(shape):
        return None, ("the residual left is explained as well by coloured measurement noise (a drift on the "
                      f"output path, {shape.estimates[0].equation}, that no state or input explains) as by a "
                      "missing term: nothing is called unexplained")
    best = shape.estimates[0]
    worst = max(above, key=lambda o: ratios[o])
    law = (f"; a smooth function of {best.variable} explains {100 * (best.share_explained or 0):.0f} % of that "
           "disturbance" if best.variable else "")
    message = (f"not explained: the final residual of {worst} is {ratios[worst]:.1f}× the noise level "
               f"({shape.noise_level[worst]:.3g}); a disturbance on {_where(best.equation)} holds "
               f"{100 * best.residual_share:.0f} % of the residual{law} — see `unexplained.shape` for its samples")
    return Unexplained(outputs=above, residual_to_noise={o: round(r, 3) for o, r in ratios.items()},
                       noise_level=shape.noise_level, shape_share=float(best.residual_share),
                       equation=best.equation, variable=best.variable, share_explained=best.share_explained,
                       message=message, shape=shape.public), ""


def _where(equation: str) -> str:
    return f"the {equation} path" if equation.startswith("output ") else f"the equation of {equation}"


def leftover_at(request, fit: FitResult, shape_fit: FitResult | None, shape: ShapeResult | None,
                clock) -> tuple[Unexplained | None, str]:
    """`what_is_left` at the final fit, with the shape already learned at it when there is one.

    Parameters
    ----------
    request : FitRequest
        The final fit's request.
    fit : FitResult
        The final fit.
    shape_fit : FitResult or None
        The fit `shape` was learned at (when `fit` is it, `shape` is reused).
    shape : ShapeResult or None
        The shape learned at `shape_fit`.
    clock : Clock
        The request's budget (the shape step is timed and skipped when it is spent).

    Returns
    -------
    tuple of (Unexplained or None, str)
        As `what_is_left`; (None, why) when no shape could be estimated.
    """
    from greyfit.solvers.discovery.shape import shape_at
    note = ""
    if shape is None or fit is not shape_fit:
        shape, note = shape_at(request, fit, clock)
    if shape is None:
        return None, note
    return what_is_left(fit, shape)
