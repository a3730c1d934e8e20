"""Small statistics without scipy: Student-t quantile and information criteria."""
from __future__ import annotations

import math
from statistics import NormalDist


def student_t_quantile(q: float, dof: float) -> float:
    """Quantile of Student's t (exact for 1 and 2 dof, Cornish-Fisher expansion above: <1e-4 rel. for dof ≥ 5).

    Parameters
    ----------
    q : float
        Probability, in (0, 1).
    dof : float
        Degrees of freedom.

    Returns
    -------
    float
        The q-quantile; NaN when `dof` ≤ 0.
    """
    if dof <= 0:
        return math.nan
    if dof == 1:
        return math.tan(math.pi * (q - 0.5))
    if dof == 2:
        return (2 * q - 1) / math.sqrt(2 * q * (1 - q))
    z = NormalDist().inv_cdf(q)
    g1 = (z ** 3 + z) / 4
    g2 = (5 * z ** 5 + 16 * z ** 3 + 3 * z) / 96
    g3 = (3 * z ** 7 + 19 * z ** 5 + 17 * z ** 3 - 15 * z) / 384
    g4 = (79 * z ** 9 + 776 * z ** 7 + 1482 * z ** 5 - 1920 * z ** 3 - 945 * z) / 92160
    return z + g1 / dof + g2 / dof ** 2 + g3 / dof ** 3 + g4 / dof ** 4


def information_criteria(rss: float, ndata: int, nvarys: int) -> tuple[float, float]:
    """(AIC, BIC) of a Gaussian least-squares fit, as lmfit reports them.

    Parameters
    ----------
    rss : float
        Residual sum of squares (floored at 1e-300 before the logarithm).
    ndata : int
        Number of residuals.
    nvarys : int
        Number of fitted variables.

    Returns
    -------
    aic : float
        n log(rss/n) + 2 k.
    bic : float
        n log(rss/n) + log(n) k.
    """
    rss = max(rss, 1e-300)
    chi = ndata * math.log(rss / ndata)
    return chi + 2 * nvarys, chi + math.log(ndata) * nvarys
