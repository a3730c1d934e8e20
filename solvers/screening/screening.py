"""One screening round: every library candidate scored on the equation residuals of the measured
states and on the output residuals (through the sensitivities), in one ranking."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from greyfit.schemas.discovery import DiscoveryOptions
from greyfit.schemas.fit import FitRequest, FitResult
from greyfit.solvers.data.experiments import prepare_experiments
from greyfit.solvers.methods.registry import simulates_outputs
from greyfit.solvers.methods.shooting import OutputErrorModel
from greyfit.solvers.model.compiler import compile_model
from greyfit.solvers.model.parameters import build_layout
from greyfit.solvers.screening.effects import Candidate, OutputFit, library
from greyfit.solvers.screening.scoring import RegressionScorer, Score
from greyfit.solvers.screening.scoring_equations import EquationScorer, build_trace
from greyfit.solvers.screening.scoring_outputs import OutputScorer, column_views


@dataclass
class Scored:
    candidate: Candidate
    score: Score
    scored_on: Literal["equations", "outputs", "refit"]
    significant: bool = False
    scorer: RegressionScorer | None = None   # the regression it was scored in (a warm start's Gauss-Newton step)



@dataclass
class Screening:
    scored: list[Scored] = field(default_factory=list)
    tries: int = 0
    notes: list[str] = field(default_factory=list)
    equations_scored: list[str] = field(default_factory=list)
    outputs_scored: list[str] = field(default_factory=list)
    white: bool = False       # every output residual passed the whiteness test
    output_scorer: OutputScorer | None = None
    states: list[str] = field(default_factory=list)
    significance: float = 0.01
    outputs: list[str] = field(default_factory=list)


def fitted_values(request: FitRequest, fit: FitResult):
    """(compiled model, data, layout, scaled θ, initial states) of a fit.

    Parameters
    ----------
    request : FitRequest
        The fit's request.
    fit : FitResult
        The fit (estimates by label, initial states by experiment).

    Returns
    -------
    tuple
        (CompiledModel, list of ExperimentData, ParameterLayout, scaled θ (nθ,), per experiment a dict
        state -> initial value, 0 where the fit gives none).

    Raises
    ------
    FitError
        When the request's model or data do not compile or prepare.
    """
    cm = compile_model(request.model)
    data = prepare_experiments(request.experiments, cm)
    layout = build_layout(request.model, [d.name for d in data])
    theta = np.array([fit.parameters[label].value for label in layout.labels])
    x0s = []
    for d in data:
        known = fit.initial_states.get(d.name, {})
        x0s.append({s: float(known.get(s, 0.0)) for s in cm.states})
    return cm, data, layout, theta / layout.scale, x0s


def screen(request: FitRequest, fit: FitResult, opts: DiscoveryOptions, exclude: set[str],
           output_scorer: OutputScorer | None = None, equations: bool = True,
           significant_only: bool = False) -> Screening:
    """Score every candidate whose family is not in `exclude`; see the module docstring.

    Parameters
    ----------
    request : FitRequest
        The fit's request.
    fit : FitResult
        The fit to screen at.
    opts : DiscoveryOptions
        Effects, user candidates, smoothing width, significance and smallest share explained.
    exclude : set of str
        Candidate families not to score (already added or rejected).
    output_scorer : OutputScorer or None
        One already built at this fit (its sensitivities are most of a screen's cost).
    equations : bool
        Also score the equation residuals where states are measured (the loop's fast screen); the
        fit's lack-of-fit check reads the output scores only, and the tries counted are those scored.
    significant_only : bool
        Leave out the output candidates that explain less than `opts.min_explained` (they cannot be
        significant): the lack-of-fit check asks only for the significant ones. Every candidate is
        still counted in the tries.

    Returns
    -------
    Screening
        The scored candidates ranked (`rank`), each marked significant at the Bonferroni level
        `opts.significance` / tries with a physical sign and at least `opts.min_explained`; the notes,
        which equations and outputs were scored, and the output scorer.

    Raises
    ------
    FitError
        When the request's model or data do not compile or prepare, or a user candidate does not compile.
    """
    cm, data, layout, theta_s, x0s = fitted_values(request, fit)
    oem = OutputErrorModel(cm, data, layout, request.options)
    params = [np.asarray(layout.full(e, theta_s), dtype=float).ravel() for e in range(len(data))]
    try:
        simulated = [oem.numeric_states(e, np.array([x0s[e][s] for s in cm.states]), params[e])
                     for e in range(len(data))]
    except RuntimeError:
        simulated = [np.zeros((cm.nx, d.n)) for d in data]
    free = [p.name for p in request.model.parameters if not p.fixed]
    out = Screening(white=all(a.whiteness.passed for a in fit.residual_analysis), states=list(cm.states),
                    outputs=list(cm.outputs), significance=opts.significance)
    effects = list(opts.effects)

    def keep(c: Candidate) -> bool:
        return c.family not in exclude and (bool(c.equations) or bool(c.outputs))

    # equation residuals where states are measured: the fast screen
    eq_trace = build_trace(cm, data, params, simulated, free, request.options, use_measurements=True) \
        if equations else None
    if eq_trace is not None and eq_trace.traced:
        scorers: dict[tuple, EquationScorer] = {}

        def scorer_for(equations) -> EquationScorer:
            key = tuple(sorted(equations))
            if key not in scorers:
                scorers[key] = EquationScorer(eq_trace, list(key))
            return scorers[key]
        cands, notes = library(request.model, eq_trace, effects, opts.candidates, opts.coulomb_epsilon,
                               scorer_for, opts.significance, opts.min_explained)
        out.notes += notes
        for c in filter(keep, cands):
            sc = scorer_for(c.equations)
            s = sc.score(sc.stack(c.equations))
            out.tries += c.tries
            if s is not None:
                out.scored.append(Scored(c, s, "equations", scorer=sc))
        out.equations_scored = [cm.states[i] for i in eq_trace.traced]

    # output residuals through the sensitivities: any state equation, measured or not, and the outputs
    if simulates_outputs(request.method) and np.all([np.all(np.isfinite(s)) for s in simulated]):
        scorer = output_scorer if output_scorer is not None else OutputScorer(oem, theta_s, x0s)
        out.output_scorer = scorer
        sim_trace = build_trace(cm, data, params, simulated, free, request.options, use_measurements=False)
        cands, notes = library(request.model, sim_trace, effects, opts.candidates, opts.coulomb_epsilon,
                               lambda equations: scorer, opts.significance, opts.min_explained,
                               OutputFit(list(cm.outputs), scorer.y, data))
        out.notes += [n for n in notes if n not in out.notes]
        cands = [c for c in cands if keep(c)]
        matrix, starts, ends, vectors = scorer.stack_matrix([(c.equations, c.outputs) for c in cands])
        columns = column_views(matrix, starts, ends, vectors)
        scores = scorer.score_many([None if c.refit_only else g for c, g in zip(cands, columns)],
                                   opts.min_explained if significant_only else 0.0, within=(matrix, starts))
        for c, s in zip(cands, scores):
            out.tries += c.tries
            if c.refit_only:
                # no linear evidence at this fit: tried by refit when the residual is not white
                out.scored.append(Scored(c, Score(scorer.rss0, scorer.rss0, scorer.r.size, scorer.n_eff, 0.0, 0.0,
                                                  1.0, 0.0, 0.0, 0.0), "refit", significant=not out.white))
                continue
            if s is not None:
                out.scored.append(Scored(c, s, "outputs", scorer=scorer))
        out.outputs_scored = list(cm.outputs)

    alpha = opts.significance / max(out.tries, 1)
    for item in out.scored:
        c, sco = item.candidate, item.score
        if c.refit_only:
            continue
        physical = c.sign == 0 or np.sign(sco.beta) == np.sign(c.sign)
        item.significant = bool(sco.p_value * c.multiplicity < alpha and sco.explained >= opts.min_explained
                                and physical)
    out.scored = rank(out.scored)
    return out


def rank(scored: list[Scored]) -> list[Scored]:
    """Largest BIC drop first; a change in time (step, drift) goes behind the significant structural
    effects when one of them explains at least half as much (a change in time is true of this record
    only, and the linearised score understates a nonlinear term such as a sharp tanh more than a
    step), and behind any structural effect only a refit can judge. A catch-all coefficient that
    switches at a threshold goes behind a named law that explains at least half as much.

    Parameters
    ----------
    scored : list of Scored
        The scored candidates.

    Returns
    -------
    list of Scored
        The same, sorted best first.
    """
    structural = [sc.score.explained for sc in scored if sc.significant and not sc.candidate.record_specific
                  and not sc.candidate.refit_only and not sc.candidate.generic]
    best = max(structural, default=0.0)
    refit_pending = any(sc.significant and sc.candidate.refit_only for sc in scored)

    def level(sc: Scored) -> int:
        if sc.candidate.refit_only:
            return 1
        if sc.candidate.record_specific and (refit_pending or best >= 0.5 * sc.score.explained):
            return 0
        if sc.candidate.generic and best >= 0.5 * sc.score.explained:
            return 0   # a named physical law before a catch-all switching coefficient
        return 2
    # BIC drops equal to rounding (two spellings of one column, u² and a law P(u) whose linear part the
    # model has) keep the registry's order, so the ranking does not depend on how the model is spelt
    return sorted(scored, key=lambda sc: (level(sc), float(f"{sc.score.bic_drop:.8g}")), reverse=True)
