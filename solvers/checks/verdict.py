"""The checks that make `good` mean right, run on the whole result after the fit (issue 22).

`assess_fit` judges the optimisation (convergence, identifiability, whiteness); this adds lack of
fit — a missing effect by the screen's score test (`lack_of_fit`), a residual above the noise
(`noise_level`) — and a held input read as ramps, then recomputes the verdict (`quality.requalify`).
"""
from __future__ import annotations

from greyfit.schemas.fit import FitRequest, FitResult, FitWarning
from greyfit.schemas.preprocess import PreprocessingReport
from greyfit.solvers.checks.lack_of_fit import missing_effect_warnings
from greyfit.solvers.checks.noise_level import noise_level_warnings
from greyfit.solvers.checks.quality import independence_warnings, requalify
from greyfit.solvers.methods.registry import simulates_outputs


def held_input_warnings(report: PreprocessingReport | None) -> list[FitWarning]:
    """`input_held_fitted_linear` where the request forced foh on inputs that look held.

    Parameters
    ----------
    report : PreprocessingReport or None
        The preprocessing report; its ``input_looks_held`` hints are turned into warnings.

    Returns
    -------
    list of FitWarning
        One warning per such hint.
    """
    hints = [h for h in (report.hints if report else []) if h.code == "input_looks_held"]
    return [FitWarning(
        code="input_held_fitted_linear",
        message=h.message.replace("look piecewise constant", "look held between samples (piecewise constant)")
        + ": read as ramps, a held input biases the estimates (a thermal node's C by 4 % in the trust "
          "benchmark) and their intervals miss the truth",
        detail=h.detail) for h in hints]


def review_fit(request: FitRequest, result: FitResult, extra: list[FitWarning] | None = None) -> FitResult:
    """`result` with the lack-of-fit and input-handling warnings added and its verdict recomputed.

    `request` is the prepared one (preprocessed, interpolation and substeps resolved).

    Parameters
    ----------
    request : FitRequest
        The prepared fit request.
    result : FitResult
        The result assessed by `assess_fit`.
    extra : list of FitWarning, optional
        Warnings found on the way that count too (an input reading that could not be refitted).

    Returns
    -------
    FitResult
        As `requalify` with the held-input, missing-effect, noise-level and residual–input
        independence warnings.
    """
    more = held_input_warnings(result.preprocessing) + list(extra or [])
    more += missing_effect_warnings(request, result) + noise_level_warnings(request, result)
    if simulates_outputs(request.method) and request.model.discrete is None and result.quality != "failed":
        # output error of an ODE (equation error's residuals are smoothed derivatives; a difference
        # equation's prediction error is the user's noise model's)
        more += independence_warnings(result)
    return requalify(result, more)
