"""The library of named physical effects, each a candidate term with its regressor and model rewrite."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from greyfit.schemas.discovery import CustomCandidate
from greyfit.schemas.model import Model
from greyfit.solvers.discovery.augment import add_term, fresh_name, replace_in_equations, replace_parameter, with_parameter
from greyfit.solvers.discovery.scoring_equations import TraceData
from greyfit.solvers.model.expressions import compile_expression, parse

import casadi as ca


MAX_SWITCHES = 6   # switch times of one parameter chosen jointly at most
# candidate switch times per parameter: every column is propagated through the output sensitivities
# and searched by forward selection, so the grid sets the cost of the step screen; 200 places a switch
# within 0.5 % of the record (seed 000's k4 within 5 ms of 1 s) at a third of the cost of 600
STEP_GRID = 200


@dataclass
class Candidate:
    effect: str
    equations: dict[int, list[np.ndarray]]   # equation index -> regressor per experiment
    term: str                                 # the term as it enters the model (for the report)
    description: str
    apply: Callable[[Model], tuple[Model, list[str]]]   # -> augmented model, new parameter names
    sign: float = 0.0          # +1/-1: the coefficient must have this sign to be physical; 0: any
    family: str = ""           # scanned variants of one candidate share a family (Bonferroni counts them)
    stiffness: float = 0.0     # |∂(term)/∂x| per unit coefficient: tanh(v/ε) adds |β|/ε to the Jacobian
    refit_variants: bool = False   # let the confirming refit choose among the family's variants
    tries: int = 1             # alternatives this candidate was selected from (counts for Bonferroni)
    transform_experiments: Callable | None = None   # data the new model needs (a delayed input)
    outputs: dict[int, list[np.ndarray]] | None = None   # direct effect on outputs (output-path effects)
    record_specific: bool = False   # a step or drift in time: true of this record, not of new data
    key: str = ""              # identifies the same term found by either scorer
    refit_only: bool = False   # its linearisation at this fit says nothing (e.g. |h| where h > 0): refit decides
    fresh_start: bool = False  # refit from the declared initial values, not from the fit it replaces
    generic: bool = False      # a catch-all shape (a switching coefficient, a shift in time), not a named law
    # hypotheses behind the candidate beyond `tries`: a set of switch times chosen jointly from a grid is
    # one of C(grid, m) subsets, not one of grid·m columns; its p-value is multiplied by this
    multiplicity: float = 1.0
    width: float = 0.0         # the ε of a smoothed switch tanh(v/ε): its variants differ only in it

    def __post_init__(self):
        self.key = self.key or f"{self.family}|{self.term}"


def _fmt(v: float) -> str:
    return f"{v:.6g}"


def structure(model: Model) -> tuple[dict[str, str], dict[str, str]]:
    """(velocity -> its position, position -> its velocity) from kinematic equations dx/dt = v."""
    vel_of, pos_of = {}, {}
    for s, text in model.equations.items():
        node = parse(text, f"equations.{s}")
        if node[0] == "name" and node[1] in model.states and node[1] != s:
            pos_of[node[1]] = s
            vel_of[s] = node[1]
    return pos_of, vel_of


def _additive(trace: TraceData, eq: int, values: list[np.ndarray]) -> dict[int, list[np.ndarray]]:
    return {eq: values}


def library(model: Model, trace: TraceData, effects: list[str], custom: list[CustomCandidate],
            epsilon: float | None, scorer_for: Callable | None = None, significance: float = 0.01,
            min_explained: float = 0.05) -> list[Candidate]:
    cm = trace.cm
    states = cm.states
    pos_of, vel_of = structure(model)
    velocities = [s for s in states if s in pos_of] or states
    traced = set(trace.traced)
    out: list[Candidate] = []
    notes: list[str] = []

    def state_values(s: str) -> list[np.ndarray]:
        return [x[states.index(s)] for x in trace.x]

    def term_candidate(effect: str, eq_state: str, regressor: list[np.ndarray], term_text: str,
                       pname: str, sign: str, lower, description: str, phys_sign: float,
                       stiffness: float = 0.0, refit_variants: bool = False, width: float = 0.0):
        eq = states.index(eq_state)
        if eq not in traced:
            return

        def apply(m: Model, term_text=term_text, pname=pname) -> tuple[Model, list[str]]:
            name = fresh_name(m, pname)
            m = with_parameter(m, name, 0.0 if lower is None else 1e-6, lower=lower)
            return add_term(m, eq_state, f"{name}*{term_text}", sign), [name]
        # a '-' term with a positive parameter contributes -g: the regression coefficient is on +g
        out.append(Candidate(effect, {eq: regressor}, f"{sign} {pname}*{term_text}", description, apply,
                             sign=phys_sign, family=f"{effect}:{eq_state}", stiffness=stiffness,
                             refit_variants=refit_variants, width=width))

    if "coulomb" in effects:
        for v in velocities:
            vals = state_values(v)
            allv = np.concatenate(vals)
            if min(np.mean(allv > 0), np.mean(allv < 0)) < 0.02:
                # on a quantity that keeps its sign, sign(v) is a constant: an offset, not friction
                notes.append(f"coulomb on {v} not tried: {v} does not change sign (that would be an offset)")
                continue
            rms = float(np.sqrt(np.mean(allv ** 2))) or 1.0
            # the smoothing width matters: one far from the data's own leaves a misfit near v = 0
            # (stick-slip) that the loop would chase with spurious terms. The screening cannot tell
            # the widths apart (the smoothed derivative blurs the jump), so the refit chooses.
            for eps in ([epsilon] if epsilon else [f * rms for f in (0.001, 0.003, 0.01, 0.03)]):
                term = f"tanh({v}/{_fmt(eps)})"
                term_candidate("coulomb", v, [np.tanh(x / eps) for x in vals], term, f"Fc_{v}", "-", 0.0,
                               f"Coulomb friction on {v}: sign({v}) smoothed as {term}", -1.0, 1.0 / eps,
                               refit_variants=True, width=eps)
    if "quadratic_drag" in effects:
        for v in velocities:
            vals = state_values(v)
            term_candidate("quadratic_drag", v, [x * np.abs(x) for x in vals], f"{v}*abs({v})", f"Cd_{v}",
                           "-", 0.0, f"quadratic drag on {v}", -1.0)
    if "cubic_stiffness" in effects:
        for v, x_name in pos_of.items():
            vals = state_values(x_name)
            term_candidate("cubic_stiffness", v, [x ** 3 for x in vals], f"{x_name}^3", f"k3_{x_name}", "-",
                           None, f"cubic (hardening or softening) stiffness on {x_name}", 0.0)
    if "offset" in effects:
        for i in sorted(traced):
            s = states[i]
            if s in vel_of:
                continue   # a kinematic identity dx/dt = v has no force to be offset
            term_candidate("offset", s, [np.ones_like(t) for t in trace.t], "1", f"f0_{s}", "+", None,
                           f"constant offset in d{s}/dt", 0.0)
    if "sqrt_flow" in effects:
        for s in states:
            cand = _sqrt_flow(trace, s, pos_of, vel_of)
            if cand is not None:
                out.append(cand)
    for ci, cand in enumerate(custom):
        if states.index(cand.equation) not in traced:
            continue
        env = _numeric_env(trace)
        vals = [np.asarray(v, dtype=float) for v in
                _evaluate(cand.term, env, len(trace.t), f"discovery.candidates[{ci}].term")]

        def apply_custom(m: Model, cand=cand) -> tuple[Model, list[str]]:
            name = fresh_name(m, cand.parameter)
            m = with_parameter(m, name, cand.value, cand.lower, cand.upper)
            return add_term(m, cand.equation, f"{name}*({cand.term})", "+"), [name]
        out.append(Candidate("custom", {states.index(cand.equation): vals}, f"+ {cand.parameter}*({cand.term})",
                             f"user candidate {cand.parameter}*({cand.term}) in d{cand.equation}/dt",
                             apply_custom, family=f"custom:{cand.parameter}"))
    out += _parameter_effects(model, trace, effects, scorer_for, significance, min_explained)
    out += _input_effects(model, trace, effects)
    return out, notes


def _sqrt_flow(trace: TraceData, s: str, pos_of: dict, vel_of: dict) -> Candidate | None:
    """Torricelli's law: every flow the model computes from level s follows sqrt(s), not s.

    The declared flows through s (say k1*h1, out of tank 1 and into tank 2) change law together,
    so mass stays conserved: s -> sqrt(max(s, 0)) in the equations. Scored as the family
    s -> s + β (sqrt(s) − s): forcing ∂f/∂s · (sqrt(s) − s); the flow coefficients absorb the
    linear part, so the score does not depend on the units of s.
    """
    cm = trace.cm
    k = cm.states.index(s)
    allv = np.concatenate([x[k] for x in trace.x])
    if s in pos_of or s in vel_of or np.mean(allv > 0) < 0.9:
        return None   # Torricelli outflow is for levels: positive, non-mechanical states
    change = [np.sqrt(np.maximum(x[k], 0)) - x[k] for x in trace.x]
    reg = _sensitivity_regressor(trace, trace.jx, k, change)
    if not reg:
        return None
    flows_into = sorted(cm.states[i] for i in reg if cm.states[i] != s)

    # a floor far below the levels seen keeps sqrt's slope finite where a level starts at 0
    floor = _fmt(1e-6 * float(np.sqrt(np.mean(allv ** 2))))

    def apply(m: Model, s=s) -> tuple[Model, list[str]]:
        return replace_in_equations(m, s, f"sqrt(max({s}, {floor}))"), []
    where = f"d{s}/dt" + "".join(f", d{o}/dt" for o in flows_into)
    return Candidate("sqrt_flow", reg, f"{s} -> sqrt(max({s}, 0)) in the flows of {where}",
                     f"Torricelli outflow: the flows through {s} follow sqrt({s})", apply, sign=1.0,
                     family=f"sqrt_flow:{s}")


def _numeric_env(trace: TraceData) -> dict:
    cm = trace.cm
    env = {"t": trace.t}
    for i, s in enumerate(cm.states):
        env[s] = [x[i] for x in trace.x]
    for i, u in enumerate(cm.inputs):
        env[u] = [uu[i] for uu in trace.u]
    for j, p in enumerate(cm.parameters):
        env[p] = [np.full(t.size, pv[j]) for t, pv in zip(trace.t, trace.p)]
    env.update({k: [np.full(t.size, v) for t in trace.t] for k, v in cm.model.constants.items()})
    return env


def _evaluate(text: str, env: dict, n_exp: int, where: str) -> list[np.ndarray]:
    names = list(env)
    syms = [ca.SX.sym(n) for n in names]
    expr = compile_expression(text, dict(zip(names, syms)), where)
    fn = ca.Function("term", syms, [expr])
    out = []
    for e in range(n_exp):
        n = env["t"][e].size
        out.append(np.array(fn.map(n)(*[np.asarray(env[k][e])[None, :] for k in names])).ravel())
    return out


def _sensitivity_regressor(trace: TraceData, jacobians: list[np.ndarray], j: int,
                           change: list[np.ndarray]) -> dict[int, list[np.ndarray]]:
    """∂f_i/∂z_j · change(t) for every traced equation that depends on z_j (a parameter or input)."""
    reg = {}
    for i in trace.traced:
        cols = [jac[:, i, j] * c for jac, c in zip(jacobians, change)]
        if any(np.any(c != 0) for c in cols):
            reg[i] = cols
    return reg


def _param_regressor(trace: TraceData, j: int, shape: list[np.ndarray]) -> dict[int, list[np.ndarray]]:
    return _sensitivity_regressor(trace, trace.jp, j, shape)


def _step_candidate(trace: TraceData, name: str, j: int, scorer_for, significance: float,
                    min_explained: float, t_lo: float, t_hi: float) -> Candidate | None:
    """Switch times of a piecewise-constant parameter by forward selection over a time grid.

    One step rarely explains a parameter that switches back and forth (seed 000's k4 alternates
    at 0.25/0.5/0.75 s), so the switch times are chosen jointly, each kept while its partial
    F-test passes at `significance` divided by the grid size.
    """
    t_all = np.concatenate(trace.t)
    grid = np.unique(t_all[(t_all >= t_lo) & (t_all <= t_hi)])
    if grid.size > STEP_GRID:
        grid = grid[np.linspace(0, grid.size - 1, STEP_GRID).astype(int)]
    base = _param_regressor(trace, j, [np.ones_like(t) for t in trace.t])
    if not base or scorer_for is None:
        return None
    scorer = scorer_for(sorted(base))
    steps = {i: [c[:, None] * (t[:, None] >= grid[None, :]) for c, t in zip(cols, trace.t)]
             for i, cols in base.items()}
    columns = scorer.stack(steps)
    # forward selection by gain alone (a single switch of a parameter that switches back and forth
    # explains little, so no per-step test), then drop switches that add too little jointly;
    # the joint significance test and the confirming refit judge the result
    min_gain = min_explained / 2.5
    chosen = scorer.forward_select(columns, max_columns=MAX_SWITCHES, alpha=1.0, min_gain=min_gain)
    chosen = scorer.prune(columns, chosen, min_gain)
    # a value held for a few samples is a patch for a slightly misplaced switch, not a parameter change
    dwell = max(5 * float(np.median(np.diff(grid))), 0.01 * float(t_all.max() - t_all.min()))
    kept: list[int] = []
    for c in chosen:   # in order of selection: the stronger switch of a close pair stays
        if all(abs(grid[c] - grid[k]) >= dwell for k in kept):
            kept.append(c)
    chosen = scorer.prune(columns, kept, min_gain)
    if not chosen:
        return None
    taus = sorted(float(grid[c]) for c in chosen)
    grid_size = int(grid.size)
    final = {i: [np.column_stack([c * (t >= tau) for tau in taus]) for c, t in zip(cols, trace.t)]
             for i, cols in base.items()}

    def apply(m: Model, name=name, taus=taus) -> tuple[Model, list[str]]:
        names, terms = [], []
        for tau in taus:
            d = fresh_name(m, f"d{name}_step")
            m = with_parameter(m, d, 0.0)
            names.append(d)
            terms.append(f"{d}*if_else(t >= {_fmt(tau)}, 1, 0)")
        return replace_parameter(m, name, f"({name} + {' + '.join(terms)})"), names
    when = ", ".join(_fmt(tau) for tau in taus)
    # the switch times are a subset chosen jointly from the grid: its share of the level (grid·m of the
    # Bonferroni count) is split among the C(grid, m) subsets of its size, and among the sizes the
    # selection may end at. Counting grid·m alone let forward selection over-fit coloured noise.
    tries = grid_size * len(taus)
    multiplicity = max(MAX_SWITCHES * math.comb(grid_size, len(taus)) / tries, 1.0)
    return Candidate("parameter_step", final, f"{name} -> {name} + steps at t = {when}",
                     f"{name} changes value at t = {when} s", apply, family=f"parameter_step:{name}",
                     tries=tries, record_specific=True, multiplicity=multiplicity)


def _parameter_effects(model: Model, trace: TraceData, effects: list[str], scorer_for=None,
                       significance: float = 0.01, min_explained: float = 0.05) -> list[Candidate]:
    cm = trace.cm
    out: list[Candidate] = []
    shared_free = [p.name for p in model.parameters if not p.fixed and not p.per_experiment]
    t_all = np.concatenate(trace.t)
    t_lo, t_hi = np.quantile(t_all, 0.03), np.quantile(t_all, 0.97)
    for name in shared_free:
        j = cm.parameters.index(name)
        if not _param_regressor(trace, j, [np.ones_like(t) for t in trace.t]):
            continue
        if "parameter_step" in effects:
            cand = _step_candidate(trace, name, j, scorer_for, significance, min_explained, t_lo, t_hi)
            if cand is not None:
                out.append(cand)
        if "parameter_drift" in effects:
            t_mid = float(np.mean(t_all))
            reg = _param_regressor(trace, j, [t - t_mid for t in trace.t])

            def apply_drift(m: Model, name=name, t_mid=t_mid) -> tuple[Model, list[str]]:
                d = fresh_name(m, f"d{name}_dt")
                m = with_parameter(m, d, 0.0)
                return replace_parameter(m, name, f"({name} + {d}*(t - {_fmt(t_mid)}))"), [d]
            out.append(Candidate("parameter_drift", reg, f"{name} -> {name} + d{name}_dt*(t - {_fmt(t_mid)})",
                                 f"{name} drifts linearly in time", apply_drift, family=f"parameter_drift:{name}",
                                 record_specific=True))
        if "state_dependent" in effects:
            for s_idx, s in enumerate(cm.states):
                mags = np.abs(np.concatenate([x[s_idx] for x in trace.x]))
                for thr in np.unique(np.quantile(mags, np.linspace(0.1, 0.9, 17))):
                    if thr <= 0:
                        continue
                    reg = _param_regressor(trace, j, [(np.abs(x[s_idx]) > thr).astype(float) for x in trace.x])

                    def apply_sd(m: Model, name=name, s=s, thr=thr) -> tuple[Model, list[str]]:
                        d = fresh_name(m, f"d{name}_{s}")
                        m = with_parameter(m, d, 0.0)
                        # a switch smoothed over ±5 % of the threshold: a hard if_else makes the
                        # simulation discontinuous in the state and the refit crawl
                        width = _fmt(0.05 * thr)
                        return replace_parameter(
                            m, name, f"({name} + {d}*0.5*(1 + tanh((abs({s}) - {_fmt(thr)})/{width})))"), [d]
                    out.append(Candidate("state_dependent", reg,
                                         f"{name} -> {name} + d{name}_{s}*[|{s}| > {_fmt(thr)}]",
                                         f"{name} switches when |{s}| exceeds {_fmt(thr)}", apply_sd,
                                         family=f"state_dependent:{name}:{s}", generic=True))
    return out


def _input_effects(model: Model, trace: TraceData, effects: list[str]) -> list[Candidate]:
    cm = trace.cm
    out: list[Candidate] = []
    for k, u in enumerate(cm.inputs):
        def input_reg(change: list[np.ndarray], k=k) -> dict[int, list[np.ndarray]]:
            return _sensitivity_regressor(trace, trace.ju, k, change)
        mags = np.abs(np.concatenate([uu[k] for uu in trace.u]))
        if "saturation" in effects and mags.max() > 0:
            for level in np.unique(np.quantile(mags, np.linspace(0.5, 0.98, 13))):
                if level <= 0:
                    continue
                change = [np.clip(uu[k], -level, level) - uu[k] for uu in trace.u]
                reg = input_reg(change)
                if not reg:
                    continue

                def apply_sat(m: Model, u=u, level=level) -> tuple[Model, list[str]]:
                    name = fresh_name(m, f"{u}_max")
                    m = with_parameter(m, name, float(level), lower=0.0)
                    return _replace_input(m, u, f"min(max({u}, -{name}), {name})"), [name]
                out.append(Candidate("saturation", reg, f"{u} -> min(max({u}, -{u}_max), {u}_max)",
                                     f"input {u} saturates near ±{_fmt(level)}", apply_sat, sign=1.0,
                                     family=f"saturation:{u}"))
        if "input_delay" in effects:
            for lag in range(1, 21):
                change = [np.concatenate([np.full(lag, uu[k][0]), uu[k][:-lag]]) - uu[k] for uu in trace.u]
                reg = input_reg(change)
                if not reg:
                    continue
                dt = float(np.median(np.diff(trace.t[0])))
                delayed = fresh_name(model, f"{u}_delayed")

                def apply_delay(m: Model, u=u, delayed=delayed) -> tuple[Model, list[str]]:
                    m = m.model_copy(update={"inputs": [*m.inputs, delayed]})
                    return _replace_input(m, u, delayed), []

                def delay_data(experiments, u=u, delayed=delayed, lag=lag):
                    out_exps = []
                    for exp in experiments:
                        series = list(exp.inputs[u])
                        shifted = [series[0]] * lag + series[:-lag]
                        out_exps.append(exp.model_copy(update={"inputs": {**exp.inputs, delayed: shifted}}))
                    return out_exps
                # the delay is a whole number of samples: the model language has no delay operator,
                # so the delayed input enters as data (returned in `added_inputs`)
                out.append(Candidate("input_delay", reg, f"{u}(t) -> {delayed} = {u}(t - {_fmt(lag * dt)})",
                                     f"input {u} acts {lag} sample(s) ({_fmt(lag * dt)} s) late", apply_delay,
                                     sign=1.0, family=f"input_delay:{u}", refit_variants=True, generic=True,
                                     transform_experiments=delay_data))
    return out


def _replace_input(model: Model, u: str, replacement: str) -> Model:
    """Like replace_parameter, for an input (saturation)."""
    return replace_parameter(model, u, replacement)
