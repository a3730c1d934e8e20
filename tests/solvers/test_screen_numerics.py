"""The lack-of-fit screen's vectorised statistics (solvers/screening/scoring.py) against their
definitions: the effective sample size from autocorrelations summed directly in the time domain,
and the score pass that leaves out columns too weak to be significant.
"""
from dataclasses import astuple

import numpy as np
import pytest

from greyfit.solvers.screening.scoring import (
    RegressionScorer,
    effective_n,
    effective_n_many,
    effective_n_of_series,
)


def _direct_effective_n(r: np.ndarray, max_lag: int = 100) -> float:
    """The definition: autocorrelations ρ_l = Σ r_i r_{i+l} / Σ r_i², summed until the first below
    0.05, with the geometric tail of the last two."""
    r = r - r.mean()
    n = r.size
    lags = min(max_lag, n // 4)
    rho = np.array([r[:-lag] @ r[lag:] for lag in range(1, lags)]) / (r @ r)
    below = np.flatnonzero(rho < 0.05)
    if not below.size:
        return n / (1 + 2 * rho.sum())
    cut = int(below[0])
    total = rho[:cut].sum()
    if cut >= 2 and 0 < rho[cut - 1] < rho[cut - 2]:
        decay = rho[cut - 1] / rho[cut - 2]
        total += rho[cut - 1] * decay / (1 - decay)
    return n / (1 + 2 * total)


@pytest.mark.parametrize("n, phi", [(40, 0.0), (101, 0.6), (997, 0.9), (8000, 0.8)])
def test_effective_n_is_its_definition(n, phi):
    rng = np.random.default_rng(n)
    e = rng.standard_normal((n, 4))
    r = np.empty_like(e)
    r[0] = e[0]
    for i in range(1, n):   # AR(1) columns: the sum of autocorrelations is long for phi = 0.9
        r[i] = phi * r[i - 1] + e[i]
    want = np.array([_direct_effective_n(r[:, j]) for j in range(4)])
    assert np.allclose(effective_n_many(r), want, rtol=1e-10)
    assert np.allclose([effective_n(r[:, j]) for j in range(4)], want, rtol=1e-10)
    if phi >= 0.8:
        assert np.all(want < n / 3)   # the coloured case is not trivially n


def test_interleaved_outputs_are_read_as_the_series_they_are():
    """Three independent AR(1) 0.8 outputs, rows sample-major as a multi-output record has them: each
    series' effective size is n_j (1 − φ)/(1 + φ) ≈ n_j/9, so the pooled one is about n/9; read as one
    interleaved series the lag-1 correlation is between outputs (about 0) and it came out n."""
    rng = np.random.default_rng(3)
    n, phi = 3000, 0.8
    e = rng.standard_normal((n, 3))
    x = np.empty_like(e)
    x[0] = e[0]
    for i in range(1, n):
        x[i] = phi * x[i - 1] + e[i]
    x *= np.array([1.0, 2.0, 0.5])   # unequal scales: the weights are each series' share of the RSS
    rows = x.reshape(-1)             # y1, y2, y3 at t0, then at t1, ...
    series = [np.arange(j, rows.size, 3) for j in range(3)]
    pooled = float(effective_n_of_series(rows, series)[0])
    ideal = rows.size * (1 - phi) / (1 + phi)
    assert pooled == pytest.approx(ideal, rel=0.25)
    assert effective_n(rows) > 0.9 * rows.size   # the reading this replaces: the colour unseen
    # the weighted mean of per-series inflations, checked against its definition
    inflation = sum(float(rows[s] @ rows[s]) / float(rows @ rows) * s.size / effective_n(rows[s]) for s in series)
    assert pooled == pytest.approx(rows.size / inflation, rel=1e-10)
    # one series: the plain effective size
    assert float(effective_n_of_series(x[:, 0], None)[0]) == pytest.approx(effective_n(x[:, 0]), rel=1e-12)


def test_score_pass_leaves_out_only_columns_too_weak_to_count():
    rng = np.random.default_rng(5)
    n = 600
    jac = rng.standard_normal((n, 2))
    effect = np.sin(np.linspace(0, 20, n))
    r = 0.8 * effect + rng.standard_normal(n) * 0.5 + jac @ [0.3, -0.2]
    scorer = RegressionScorer(r, jac)
    columns = [effect, rng.standard_normal(n), effect + 0.5 * rng.standard_normal(n), None,
               rng.standard_normal((n, 2))]
    full = scorer.score_many(columns)
    cut = scorer.score_many(columns, least_explained=0.05)
    explained = [s.explained if s is not None else None for s in full]
    assert explained[0] > 0.3 and explained[2] > 0.05 and explained[1] < 0.05   # the case has both kinds
    for i, (a, b) in enumerate(zip(full, cut)):
        if a is None:
            assert b is None
        elif columns[i].ndim == 2 or a.explained >= 0.05:   # two-column candidates are scored as before
            assert b is not None and np.allclose(astuple(b), astuple(a), rtol=1e-12, atol=0)
        else:
            assert b is None


def test_the_gram_prefilter_keeps_every_column_that_explains_enough():
    """The pass judges the weak columns from Gram numbers (‖g‖², ‖Qᵀg‖², gᵀr₀) without forming their
    projections; near J's span those numbers cancel. Columns of every kind — nearly in the span,
    exactly in it, at the threshold, strong, weak — get the same answer as the full pass."""
    rng = np.random.default_rng(11)
    n = 2000
    jac = rng.standard_normal((n, 3))
    effect = np.cos(np.linspace(0, 30, n))
    r = 0.5 * effect + rng.standard_normal(n) * 0.6 + jac @ [0.3, -0.2, 1.0]
    scorer = RegressionScorer(r, jac)
    share = (scorer.r0 @ effect) ** 2 / (scorer.project(effect) @ scorer.project(effect)) / scorer.rss0
    columns = [effect, jac @ [1.0, 2.0, -1.0],                       # strong; exactly in the span
               jac @ [1.0, 2.0, -1.0] + 1e-2 * effect,              # in the span but for a trace of the effect
               jac @ [1.0, 0.5, 0.0] + 1e-3 * rng.standard_normal(n),
               jac @ [1.0, 2.0, -1.0] + 1e-5 * effect]              # within IN_SPAN: integration-error level
    columns += [effect + s * rng.standard_normal(n) for s in np.linspace(0.5, 3.0, 25)]   # across the threshold
    columns += [rng.standard_normal(n) for _ in range(10)]
    full = scorer.score_many(columns)
    edge = sorted(a.explained for a in full if a is not None)[len(columns) // 2]
    for least in (0.01, share / 2, 0.2, edge * (1 - 1e-9)):   # the last: one column just above it
        cut = scorer.score_many(columns, least_explained=least)
        kinds = {a is None or a.explained < least for a in full}
        assert kinds == {True, False}                                # both kinds at this threshold
        for a, b in zip(full, cut):
            if a is None or a.explained < least:
                assert b is None
            else:   # 1e-9: a column 1e-5 from J's span keeps 6 digits fewer of its projection, and
                # the products group the fewer columns otherwise
                assert b is not None and np.allclose(astuple(b), astuple(a), rtol=1e-9, atol=0)
    assert full[1] is None                                           # in J's span: nothing to score
    assert full[2] is not None and full[2].explained > 0.2          # the trace is all it has beyond J
    assert full[4] is None   # 1e-5 of its norm beyond J: what sensitivities by another route differ by


def test_columns_gathered_from_their_matrix_score_as_stacked_ones():
    """The screen hands `score_many` the matrix its columns are views of (`within`): gathered from
    it row by row, they give the same scores as the columns stacked one by one, whichever columns
    are single, wide, missing or not finite."""
    rng = np.random.default_rng(3)
    n = 800
    jac = rng.standard_normal((n, 2))
    effect = np.sin(np.linspace(0, 12, n))
    r = 0.7 * effect + rng.standard_normal(n) * 0.5 + jac @ [0.3, -0.2]
    scorer = RegressionScorer(r, jac)
    matrix = np.column_stack([effect, rng.standard_normal((n, 2)), effect + rng.standard_normal(n),
                              np.full(n, np.nan), rng.standard_normal(n)])
    starts = np.array([0, 1, 3, 4, 5, 0])
    columns = [matrix[:, 0], matrix[:, 1:3], matrix[:, 3], matrix[:, 4], matrix[:, 5], None]
    for least in (0.0, 0.05):
        stacked = scorer.score_many(columns, least_explained=least)
        gathered = scorer.score_many(columns, least_explained=least, within=(matrix, starts))
        assert [s is None for s in stacked] == [s is None for s in gathered]
        assert stacked[0] is not None and stacked[3] is None and stacked[5] is None
        for a, b in zip(stacked, gathered):
            if a is not None:
                assert astuple(a) == astuple(b)
