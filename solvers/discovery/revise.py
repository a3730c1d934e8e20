"""What happens once a refit is kept: it becomes a step (`accept`), a smoothed switch's width is
refined at the refitted model (`refine_width`), and an earlier step that lost its evidence to a later
one is dropped (`drop_superseded`). Every refit here is set up, counted and validated as the
confirming ones are (`confirm.refit_request`, `confirm.counted_refit`, `confirm.timed_validation`).
"""
from __future__ import annotations

import numpy as np

from greyfit.schemas.discovery import (
    DiscoverRequest,
    DiscoveryStep,
    Evidence,
    NewParameter,
    RejectedCandidate,
)
from greyfit.schemas.fit import FitRequest, FitResult
from greyfit.schemas.model import Model
from greyfit.solvers.discovery.confirm import (
    LoopState,
    Refitted,
    bic,
    counted_refit,
    refit_request,
    screen_state,
    t_value_of,
    timed_validation,
    with_estimates,
)
from greyfit.solvers.discovery.refit_test import output_residual
from greyfit.solvers.discovery.summary import equation_names, summarize, validation_worse
from greyfit.solvers.errors import FitError
from greyfit.solvers.screening.screening import Scored, Screening


def accept(request: DiscoverRequest, state: LoopState, r: Refitted, screening: Screening, note: str = "",
           **verdict) -> None:
    """Add the refitted candidate as a step; `verdict`: the step's verdict, runners_up, separate_by;
    `note` is appended to its description.

    Parameters
    ----------
    request : DiscoverRequest
        The discovery request (options, declared model, validation experiments).
    state : LoopState
        The search so far (model, request, fit, steps, refits left, budget).
        Updated in place: the step, the model, fit, request and validation; a smoothed switch's width is
        refined and superseded steps are dropped after.
    r : Refitted
        The refitted candidate.
    screening : Screening
        The screen the candidate came from.
    note : str
        Appended to the step's description in parentheses; "" for none.
    **verdict
        `verdict`, `runners_up` and `separate_by` of the `DiscoveryStep`.
    """
    sc, c = r.sc, r.sc.candidate
    state.steps.append(DiscoveryStep(
        effect=c.effect, equation=equation_names(screening, c), term=c.term,
        description=c.description + (f" ({note})" if note else ""),
        parameters=new_parameters(r.fit, r.params),
        evidence=Evidence(scored_on=sc.scored_on, explained_variance=sc.score.explained,
                          screening_bic_drop=sc.score.bic_drop, p_value=sc.score.p_value,
                          bic_before=bic(state.fit), bic_after=bic(r.fit), bic_drop=r.bic_drop,
                          t_value=r.t_value, noise_model_order=r.order, refit_p_value=r.lr_p,
                          residual_correlation_before=sc.score.corr_before,
                          residual_correlation_after=correlation_after(sc, r.request, r.fit, screening)),
        after=summarize(r.fit, r.validation), record_specific=c.record_specific, **verdict))
    state.accepted.append(c)
    if c.record_specific:
        state.record_params |= set(r.params)
        if "t" in c.variables:
            state.time_params |= set(r.params)
    # no steps of a step, no drift of a drift
    state.tried.update(f"{kind}:{n}" for n in r.params for kind in ("parameter_step", "parameter_drift"))
    model_before = state.model
    state.model, state.fit, state.request, state.validation = r.model, r.fit, r.request, r.validation
    if c.width > 0:
        refine_width(request, state, sc, model_before)
    drop_superseded(request, state)


def refine_width(request: DiscoverRequest, state: LoopState, sc: Scored, model_before: Model) -> None:
    """Swap the width of the smoothed switch just added while a sibling width explains a significant
    part (p below `significance` over the siblings, at least `min_explained`) of the refitted model's
    residual with the physical sign, and its refit lowers the BIC (at most two swaps).

    At the refitted model the current width's column is in the span of its own parameter, so a
    sibling's score measures exactly what a change of width would explain.

    Parameters
    ----------
    request : DiscoverRequest
        The discovery request (options, declared model, validation experiments).
    state : LoopState
        The search so far (model, request, fit, steps, refits left, budget).
        Updated in place when a width is swapped (the last step, model, fit, request, validation).
    sc : Scored
        The scored candidate just accepted.
    model_before : Model
        The model before that candidate was added.
    """
    opts = request.discovery
    current = state.accepted[-1]
    for _ in range(2):
        if state.refits_left <= 0 or not state.clock.allows():
            return
        rescreen = screen_state(state, opts.model_copy(update={"effects": [current.effect], "candidates": []}), set())
        # the widths are fractions of the RMS of the velocity at the fit they are computed on: the
        # current one comes back slightly moved, the others a factor ≥ 3 away
        # on the outputs where there is a simulation: the smoothed derivative of the equation
        # residual blurs the switch, and cannot tell widths apart
        on = "outputs" if rescreen.outputs_scored else sc.scored_on
        siblings = [x for x in rescreen.scored if x.candidate.family == current.family
                    and x.scored_on == on and x.candidate.width > 0
                    and max(x.candidate.width / current.width, current.width / x.candidate.width) > 1.5]
        if not siblings:
            return
        # a swap adds friction at the other width (the physical sign); a sibling of the opposite sign
        # only reshapes the current switch as a mixture of two widths
        alpha = opts.significance / len(siblings)
        useful = [x for x in siblings if (x.candidate.sign == 0 or np.sign(x.score.beta) == np.sign(x.candidate.sign))
                  and x.score.p_value < alpha and x.score.explained >= opts.min_explained]
        if not useful:
            return
        # widths far below what the sampling resolves explain the same: of those within 5 % of the
        # best, the widest, which needs the fewest RK4 substeps
        top = max(x.score.explained for x in useful)
        best = max((x for x in useful if x.score.explained >= 0.95 * top), key=lambda x: x.candidate.width)
        new_model, new_params = best.candidate.apply(with_estimates(model_before, state.fit))
        new_model = with_estimates(new_model, state.fit)   # the coefficient of the width it replaces
        # next to the answer: Newton, see confirm.run_refit
        new_req = refit_request(state, new_model, best.candidate, sc.score.beta, hessian="exact")
        new_fit = counted_refit(state, new_req)
        if isinstance(new_fit, str) or new_fit.quality == "failed" or bic(new_fit) >= bic(state.fit):
            return
        new_validation = timed_validation(request, state, new_model, new_fit, fitted_with=new_req)
        if validation_worse(state.validation, new_validation, opts.validation_tolerance):
            return
        step = state.steps[-1]
        c = best.candidate
        evidence = step.evidence.model_copy(update={
            "bic_after": new_fit.metrics.bic, "bic_drop": step.evidence.bic_before - bic(new_fit),
            "t_value": t_value_of(new_fit, new_params)})
        state.steps[-1] = step.model_copy(update={
            "term": c.term, "description": c.description, "parameters": new_parameters(new_fit, new_params),
            "evidence": evidence, "after": summarize(new_fit, new_validation)})
        state.accepted[-1] = current = c
        # later refits go back to the requested Hessian (Newton was for this start next to the answer)
        new_req = new_req.model_copy(update={"options": new_req.options.model_copy(
            update={"hessian": state.request.options.hessian})})
        state.model, state.fit, state.request, state.validation = new_model, new_fit, new_req, new_validation


def drop_superseded(request: DiscoverRequest, state: LoopState) -> None:
    """An earlier step whose parameter lost its evidence once a later effect came in is dropped,
    when the model without it is as good (BIC within `min_bic_drop`): e.g. a stiffness that switches
    with |y|, taken first, and then a cubic spring that explains it properly.

    Parameters
    ----------
    request : DiscoverRequest
        The discovery request (options, declared model, validation experiments).
    state : LoopState
        The search so far (model, request, fit, steps, refits left, budget).
        Updated in place: a dropped step moves to `rejected` ("superseded") and the model is refitted
        without it.
    """
    opts = request.discovery
    if any(c.transform_experiments for c in state.accepted):
        return   # the data were rewritten for a delayed input: no replay
    for idx in reversed(range(len(state.steps) - 1)):
        step = state.steps[idx]
        names = [p.name for p in step.parameters]
        t_value = t_value_of(state.fit, names) if all(n in state.fit.parameters for n in names) else None
        if t_value is None and names and all(_at_zero(state.fit, n) for n in names):
            t_value = 0.0   # driven onto its bound of 0 by a later effect: no standard error, no evidence
        if not names or t_value is None or t_value >= opts.min_t_value or state.refits_left <= 0:
            continue
        if not state.clock.allows():
            return
        model = request.model
        for k, c in enumerate(state.accepted):
            if k != idx:
                model, _ = c.apply(model)
        model = with_estimates(model, state.fit)
        new_req = state.request.model_copy(update={"model": model})
        new_fit = counted_refit(state, new_req)
        if isinstance(new_fit, str) or new_fit.quality == "failed" \
                or bic(new_fit) > bic(state.fit) + opts.min_bic_drop:
            continue
        state.rejected.append(RejectedCandidate(
            effect=step.effect, equation=step.equation, term=step.term, reason="superseded",
            detail=f"kept at first; after the effects added later its parameter has t = {t_value:.1f} and the "
                   f"model without it is as good (BIC {state.fit.metrics.bic:.1f} -> {new_fit.metrics.bic:.1f})"))
        del state.steps[idx]
        del state.accepted[idx]
        state.model, state.fit, state.request = model, new_fit, new_req
        state.validation = timed_validation(request, state, model, new_fit, fitted_with=new_req)


def _at_zero(fit: FitResult, name: str) -> bool:
    p = fit.parameters.get(name)
    return p is not None and abs(p.value) < 1e-6 and not p.stderr


def new_parameters(fit: FitResult, names: list[str]) -> list[NewParameter]:
    """The new parameters of a step as the result reports them.

    Parameters
    ----------
    fit : FitResult
        The refit.
    names : list of str
        The new parameters' names.

    Returns
    -------
    list of NewParameter
        Name, value, standard error and 95 % interval of each.
    """
    return [NewParameter(name=n, value=fit.parameters[n].value, stderr=fit.parameters[n].stderr,
                         ci95=fit.parameters[n].ci95) for n in names]


def correlation_after(sc: Scored, new_req: FitRequest, new_fit: FitResult, screening: Screening) -> float | None:
    """Correlation of the refitted model's output residual with the candidate's column (was: corr_before).
    One simulation of the refitted model; the column is the candidate's through the output
    sensitivities, also for one ranked best on the equation residuals. None where it is not defined.

    Parameters
    ----------
    sc : Scored
        The candidate as screened.
    new_req : FitRequest
        The refit's request.
    new_fit : FitResult
        The refit.
    screening : Screening
        The screen (its output scorer gives the column).

    Returns
    -------
    float or None
        The correlation; None without an output scorer, for a candidate with no column there, on a
        size mismatch, a constant column or residual, or when the refit cannot be simulated.
    """
    try:
        if screening.output_scorer is None:   # the candidate's column through the outputs, whichever
            return None                       # residual screened it best
        g = screening.output_scorer.stack(sc.candidate.equations, sc.candidate.outputs)
        r = output_residual(new_req, new_fit)
        if g is None or g.size != r.size or np.std(g) == 0 or np.std(r) == 0:
            return None
        return float(np.corrcoef(r, g)[0, 1])
    except (FitError, RuntimeError, ValueError):
        return None
