"""Is the residual as small as the noise? Three estimates of the noise, where the data give one.

- replicates: records with the same time grid, inputs and initial state differ by noise only, so
  half the mean square of their difference estimates σ² whatever the noise's colour (the classical
  pure-error lack-of-fit test);
- a validation record: a right model leaves the same residual level on data it was not fitted to;
- the high-frequency residual: σ² ≤ mean(Δ²y)²/6 for white noise plus a smooth signal
  (`quality.noise_level`). A residual that is white and yet significantly larger than this is a
  misfit faster than the sampling (an input read as ramps that is held, an aliased integration).
  A coloured residual above it may be coloured noise: the score test judges those.

Each test compares variances at about z = 4 standard errors of their ratio (a right model trips it
in well under 0.1 % of records), and never at a ratio below its floor.
"""
from __future__ import annotations

import math

import numpy as np

from greyfit.schemas.fit import FitRequest, FitResult, FitWarning
from greyfit.solvers.checks.lack_of_fit import negligible_residual
from greyfit.solvers.checks.quality import noise_level
from greyfit.solvers.data.experiments import series_array
from greyfit.solvers.methods.registry import method_family

Z = 4.0
MIN_SAMPLES = 50
HF_VARIANCE = 140.0 / 36.0   # N·Var(σ̂²_hf)/σ⁴ of the second-difference estimate on white noise
VALIDATION_FLOOR = 1.5       # a validation record may differ a little in its noise
REPLICATE_FLOOR = 1.2


def _bound(*terms: float) -> float:
    return 1.0 + Z * math.sqrt(sum(terms))


def _series(values) -> np.ndarray:
    return series_array(values)   # None (a missing sample) becomes NaN


def _warning(output: str, test: str, ratio: float, bound: float, noise: float, rmse: float, what: str,
             code: str = "residual_above_noise") -> FitWarning:
    return FitWarning(
        code=code,
        message=f"output '{output}': the residual (RMSE {rmse:.3g}) is {math.sqrt(ratio):.2f}× the noise level "
                f"{what} ({noise:.3g}); {test} test, variance ratio {ratio:.2f} > {bound:.2f}: the model "
                "misses part of the data",
        detail={"output": output, "test": test, "variance_ratio": ratio, "bound": bound, "noise_std": noise,
                "rmse": rmse})


def high_frequency_warnings(request: FitRequest, result: FitResult) -> list[FitWarning]:
    """The high-frequency test: a white residual significantly above the noise level of the data.

    Applied per output with at least `MIN_SAMPLES` measured samples and a passed whiteness test; the
    noise variance is the mean of `quality.noise_level`² over the records.

    Parameters
    ----------
    request : FitRequest
        The fit request (its measured outputs).
    result : FitResult
        Its result (RMSE and whiteness per output).

    Returns
    -------
    list of FitWarning
        One ``residual_above_noise`` warning per output whose RMSE² / σ² exceeds the bound.
    """
    out = []
    for a in result.residual_analysis:
        series = [_series(e.outputs[a.output]) for e in request.experiments if a.output in e.outputs]
        n = int(sum(np.isfinite(s).sum() for s in series))
        if a.rmse is None or n < MIN_SAMPLES or not a.whiteness.passed or not a.whiteness.lags:
            continue
        levels = [noise_level(s) for s in series if np.isfinite(s).sum() >= 5]
        sigma2 = float(np.mean(np.square(levels))) if levels else math.nan
        if not (math.isfinite(sigma2) and sigma2 > 0):
            continue
        ratio, bound = a.rmse ** 2 / sigma2, _bound(HF_VARIANCE / n, 2.0 / n)
        if ratio > bound:
            out.append(_warning(a.output, "high-frequency", ratio, bound, math.sqrt(sigma2), a.rmse,
                                "that the data's second differences show"))
    return out


def validation_warnings(request: FitRequest, result: FitResult) -> list[FitWarning]:
    """The validation test: the RMSE on the validation records significantly above the fit's own.

    Parameters
    ----------
    request : FitRequest
        The fit request (its validation records).
    result : FitResult
        Its result, with `validation` metrics.

    Returns
    -------
    list of FitWarning
        One ``validation_misfit`` warning per output whose variance ratio exceeds the bound (at least
        `VALIDATION_FLOOR`); empty without validation.
    """
    if result.validation is None:
        return []
    out = []
    n_fit = result.metrics.ndata / max(len(result.metrics.rmse), 1)
    expected = _expected_ratio(result, n_fit, sum(len(v.time) for v in request.validation))
    for name, rmse_val in result.validation.rmse.items():
        rmse = result.metrics.rmse.get(name)
        n_val = sum(int(np.isfinite(_series(v.outputs[name])).sum()) for v in request.validation
                    if name in v.outputs)
        if rmse is None or not rmse > 0 or not math.isfinite(rmse_val):
            continue
        ratio = rmse_val ** 2 / rmse ** 2
        kappa = _variance_inflation(result, name)
        bound = expected * max(VALIDATION_FLOOR, _bound(2.0 * kappa / max(n_val, MIN_SAMPLES),
                                                        2.0 * kappa / max(n_fit, 1.0)))
        if ratio > bound:
            out.append(FitWarning(
                code="validation_misfit",
                message=f"output '{name}': the RMSE on the validation records ({rmse_val:.3g}) is "
                        f"{math.sqrt(ratio):.2f}× the fit's own ({rmse:.3g}); variance ratio {ratio:.2f} > "
                        f"{bound:.2f}: the model does not carry over to data it was not fitted to",
                detail={"output": name, "test": "validation", "variance_ratio": ratio, "bound": bound,
                        "validation_rmse": rmse_val, "rmse": rmse}))
    return out


def _expected_ratio(result: FitResult, n_fit: float, n_val: int) -> float:
    """What a right model's validation variance ratio is on average: (1 + p/n_val) / (1 − p/n_fit), the
    fit's residual shrunk and the validation's grown by the estimates' error, p = tr(C C₀⁻¹) the
    effective number of parameters (C the reported covariance, C₀ the white-noise one: p is the number
    of parameters for a white residual, several times it for a coloured one, whose estimates fit the
    noise's slow part: 1.3-1.9 on a 121-sample record under AR(1) 0.8, issue 38)."""
    p = float(result.metrics.nvarys or 0)
    if result.covariance is not None and result.covariance_classical is not None:
        try:
            p = float(np.trace(np.linalg.solve(np.asarray(result.covariance_classical.matrix),
                                               np.asarray(result.covariance.matrix))))
        except np.linalg.LinAlgError:
            pass
    return (1.0 + p / max(n_val, 1)) / max(1.0 - p / max(n_fit, 1.0), 0.5)


def _variance_inflation(result: FitResult, output: str) -> float:
    """1 + 2 Σ ρ_k² over the residual's autocorrelation: how much more a mean square of coloured noise
    varies than one of white noise (AR(1) 0.8: 4.6×), so that a coloured right model's validation
    record is not read as a misfit (issue 38: 1 in 20 such fits was)."""
    for a in result.residual_analysis:
        if a.output == output and len(a.autocorrelation) > 1:
            rho = np.asarray(a.autocorrelation[1:], dtype=float)
            return 1.0 + 2.0 * float(rho @ rho)
    return 1.0


def _replicate_groups(request: FitRequest) -> list[list[int]]:
    groups: dict[tuple, list[int]] = {}
    for i, e in enumerate(request.experiments):
        key = (tuple(e.time), tuple(sorted((k, tuple(v)) for k, v in e.inputs.items())),
               tuple(sorted(e.initial_state.items())))
        groups.setdefault(key, []).append(i)
    return [g for g in groups.values() if len(g) > 1]


def replicate_warnings(request: FitRequest, result: FitResult) -> list[FitWarning]:
    """The replicate test: the residual significantly above the noise shown by replicated records.

    Records with the same time grid, inputs and initial state are replicates; the scaled
    differences from their mean estimate σ².

    Parameters
    ----------
    request : FitRequest
        The fit request (its experiments).
    result : FitResult
        Its result (RMSE per output).

    Returns
    -------
    list of FitWarning
        One ``residual_above_noise`` warning per output with at least `MIN_SAMPLES` replicate
        differences whose variance ratio exceeds the bound (at least `REPLICATE_FLOOR`).
    """
    if len(request.experiments) < 2:
        return []   # no replicates (and no need to key a long record by its every sample)
    groups = _replicate_groups(request)
    out = []
    for name, rmse in result.metrics.rmse.items():
        diffs = []
        for g in groups:
            ys = [_series(request.experiments[i].outputs[name]) for i in g if name in request.experiments[i].outputs]
            mean = np.nanmean(np.vstack(ys), axis=0) if len(ys) > 1 else None
            diffs += [(y - mean) * math.sqrt(len(ys) / (len(ys) - 1)) for y in ys] if mean is not None else []
        d = np.concatenate(diffs) if diffs else np.zeros(0)
        d = d[np.isfinite(d)]
        if rmse is None or d.size < MIN_SAMPLES:
            continue
        sigma2 = float(np.mean(d ** 2))
        ratio = rmse ** 2 / sigma2 if sigma2 > 0 else math.inf
        bound = max(REPLICATE_FLOOR, _bound(2.0 / d.size, 2.0 / max(result.metrics.ndata, 1)))
        if ratio > bound:
            out.append(_warning(name, "replicate", ratio, bound, math.sqrt(sigma2), rmse,
                                "that the replicated records' differences show"))
    return out


def noise_level_warnings(request: FitRequest, result: FitResult) -> list[FitWarning]:
    """`residual_above_noise` / `validation_misfit` where the data give a noise estimate.

    Parameters
    ----------
    request : FitRequest
        The fit request.
    result : FitResult
        Its result.

    Returns
    -------
    list of FitWarning
        The high-frequency, validation and replicate warnings; none for equation error, a failed fit,
        a negligible residual, or a fit with every parameter fixed.
    """
    if method_family(request.method) == "equation_error":
        return []   # its channels are smoothed derivatives, not the measured outputs
    if result.quality == "failed" or negligible_residual(result):
        return []
    if all(p.fixed for p in result.parameters.values()):
        return []   # nothing estimated: a simulation reported like a fit, judged by no check
    return (high_frequency_warnings(request, result) + validation_warnings(request, result)
            + replicate_warnings(request, result))
