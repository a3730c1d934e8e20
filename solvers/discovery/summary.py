"""Reporting pieces of the loop: validation metrics, before/after summaries, the public screen."""
from __future__ import annotations

import numpy as np

from greyfit.schemas.discovery import CandidateScore, DiscoverRequest, DiscoveryStep, FitSummary, ValidationSummary
from greyfit.schemas.fit import FitRequest, FitResult
from greyfit.schemas.model import Model
from greyfit.solvers.errors import FitError
from greyfit.solvers.screening.effects import Candidate
from greyfit.solvers.screening.screening import Scored, Screening


def equation_names(screening: Screening, cand: Candidate) -> str:
    """Where a candidate acts, for the report: its equations' states, then its outputs.

    Parameters
    ----------
    screening : Screening
        The screen (state and output names).
    cand : Candidate
        The candidate.

    Returns
    -------
    str
        E.g. ``"v"`` or ``"v; output y"``.
    """
    parts = []
    if cand.equations:
        parts.append(", ".join(screening.states[i] for i in sorted(cand.equations)))
    if cand.outputs:
        parts.append(", ".join(f"output {screening.outputs[j]}" for j in sorted(cand.outputs)))
    return "; ".join(parts)


def validate(request: DiscoverRequest, model: Model, fit: FitResult, experiments,
             neutral: set[str] | frozenset[str] = frozenset()) -> ValidationSummary | None:
    """Simulation metrics on the validation experiments (initial states estimated on a leading window).

    `neutral`: parameters set to 0 there, those of record-specific terms (a step at t = 3 s of the
    estimation record says nothing about t = 3 s of another record).

    Parameters
    ----------
    request : DiscoverRequest
        The discovery request (its fit options).
    model : Model
        The model to validate.
    fit : FitResult
        Its fit (the shared parameter values are used).
    experiments : list of Experiment
        The validation experiments; empty: no validation.
    neutral : set of str
        Parameters set to 0 on the validation records.

    Returns
    -------
    ValidationSummary or None
        RMSE, fit percent and NRMSE per output; None without experiments or when the simulation fails.
    """
    if not experiments:
        return None
    from greyfit.solvers.simulation.simulate import validation_metrics
    values = {name: (0.0 if name in neutral else p.value) for name, p in fit.parameters.items()
              if p.experiment is None}
    try:
        res = validation_metrics(model, values, experiments, request.options)
    except (FitError, RuntimeError, ValueError):
        return None
    return ValidationSummary(rmse=res.rmse, fit_percent=res.fit_percent, nrmse=res.nrmse)


def validation_worse(before: ValidationSummary | None, after: ValidationSummary | None, tol: float) -> str:
    """The outputs whose validation NRMSE got worse by more than a relative tolerance.

    Parameters
    ----------
    before, after : ValidationSummary or None
        Validation before and after a change.
    tol : float
        Relative tolerance (0.05: 5 % worse).

    Returns
    -------
    str
        "output: NRMSE a -> b" for each such output, joined by "; "; "" when none or either is None.
    """
    if before is None or after is None:
        return ""
    worse = [f"{o}: NRMSE {before.nrmse[o]:.4g} -> {after.nrmse[o]:.4g}" for o in before.nrmse
             if o in after.nrmse and after.nrmse[o] > before.nrmse[o] * (1 + tol)]
    return "; ".join(worse)


def summarize(fit: FitResult, validation: ValidationSummary | None = None) -> FitSummary:
    """The before/after summary of a fit.

    Parameters
    ----------
    fit : FitResult
        The fit.
    validation : ValidationSummary or None
        Its validation metrics, if any.

    Returns
    -------
    FitSummary
        Success, status, RMSE, fit percent, cost, AIC, BIC, whiteness per output and the validation.
    """
    return FitSummary(success=fit.success, status=fit.status, rmse=fit.metrics.rmse,
                      fit_percent=fit.metrics.fit_percent, cost=fit.metrics.cost, aic=fit.metrics.aic,
                      bic=fit.metrics.bic, white={a.output: a.whiteness.passed for a in fit.residual_analysis},
                      validation=validation)


def public_scores(screening: Screening) -> list[CandidateScore]:
    """The screen as the result shows it: the first-ranked variant of each family and scorer, at most 15.

    Parameters
    ----------
    screening : Screening
        The screen, ranked.

    Returns
    -------
    list of CandidateScore
        Effect, equation, term, explained variance, BIC drop, p-value and significance of each.
    """
    best_per_family: dict[str, Scored] = {}
    for sc in screening.scored:
        best_per_family.setdefault(f"{sc.candidate.family}|{sc.scored_on}", sc)
    return [CandidateScore(effect=sc.candidate.effect, equation=equation_names(screening, sc.candidate),
                           term=sc.candidate.term, explained_variance=sc.score.explained,
                           bic_drop=sc.score.bic_drop, p_value=sc.score.p_value, significant=sc.significant,
                           scored_on=sc.scored_on, record_specific=sc.candidate.record_specific)
            for sc in list(best_per_family.values())[:15]]


def added_inputs(request: DiscoverRequest, final: FitRequest) -> dict:
    """The inputs the final model needs that the request's experiments did not have (a delayed input).

    Parameters
    ----------
    request : DiscoverRequest
        The original request.
    final : FitRequest
        The final fit's request.

    Returns
    -------
    dict
        Experiment name -> {input name: samples}, for the experiments that gained inputs.
    """
    out = {}
    original = {e.name: set(e.inputs) for e in request.experiments}
    for exp in final.experiments:
        extra = {k: v for k, v in exp.inputs.items() if k not in original[exp.name]}
        if extra:
            out[exp.name] = extra
    return out


def steps_conclusion(steps) -> str:
    """'added …' naming each step, and for an ambiguous one the law that explains the data as well.

    Parameters
    ----------
    steps : list of DiscoveryStep
        The accepted steps.

    Returns
    -------
    str
        "added effect (description); ..." with the runner-up and how to separate them where ambiguous.
    """
    parts = []
    for s in steps:
        text = f"{s.effect} ({s.description})"
        if s.verdict == "ambiguous" and s.runners_up:
            other = s.runners_up[0]
            text += (f" — ambiguous: {other.effect} ({other.term}) explains these data as well "
                     f"(ΔBIC {other.delta_bic:.1f}); {s.separate_by}" if other.delta_bic is not None else "")
        parts.append(text)
    return "added " + "; ".join(parts)


def mean_nrmse(v: ValidationSummary | None) -> float | None:
    """Mean NRMSE over the outputs of a validation summary.

    Parameters
    ----------
    v : ValidationSummary or None
        The validation metrics.

    Returns
    -------
    float or None
        The mean of the finite NRMSEs; None without any.
    """
    vals = [x for x in (v.nrmse.values() if v is not None else []) if x is not None and np.isfinite(x)]
    return float(np.mean(vals)) if vals else None


def with_units(model: Model, fit: FitResult,
               steps: list[DiscoveryStep]) -> tuple[Model, FitResult, list[DiscoveryStep]]:
    """The final model, fit and steps with a unit on each added parameter that its equation fixes
    (`solvers.model.units`): an added parameter declares none, and the report showed it bare.

    Parameters
    ----------
    model : Model
        The augmented model.
    fit : FitResult
        Its fit.
    steps : list of DiscoveryStep
        The steps that added the parameters.

    Returns
    -------
    (Model, FitResult, list of DiscoveryStep)
        Copies with the units set (the same objects where none was found).
    """
    from greyfit.solvers.model.units import parameter_units
    units = parameter_units(model)
    if not units:
        return model, fit, steps
    model = model.model_copy(update={"parameters": [
        p.model_copy(update={"unit": units[p.name]}) if p.name in units else p for p in model.parameters]})
    estimates = {k: e.model_copy(update={"unit": units[k.split("[", 1)[0]]}) if e.unit is None and
                 k.split("[", 1)[0] in units else e for k, e in fit.parameters.items()}
    fit = fit.model_copy(update={"parameters": estimates,
                                 "model": model if isinstance(fit.model, Model) else fit.model})
    steps = [s.model_copy(update={"parameters": [p.model_copy(update={"unit": units.get(p.name, p.unit)})
                                                 for p in s.parameters]}) for s in steps]
    return model, fit, steps
