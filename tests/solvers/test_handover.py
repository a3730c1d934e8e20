"""Cold start: the first fit of a new structure interprets while gcc compiles, and moves to the
compiled NLP only where a solve begins anyway (solvers/methods/shooting/handover.py), never mid-solve.

The compiler is real gcc behind a gate (a wrapper that waits for a file), so a test decides when a
compile may finish; truth is the simulated record and the interpreted fit of the same request
(`GREYFIT_COMPILE=never`), which every fit must equal bit for bit whenever gcc finishes.
"""
import stat
import threading
from collections import OrderedDict

import pytest

from greyfit.solvers.dynamics import compiled as compiled_mod
from greyfit.solvers.fit import fit_model
from greyfit.solvers.methods.shooting import structured
from greyfit.solvers.nlp import solver as solver_mod
from tests.solvers.test_compiled import _request
from tests.systems import MSD_TRUTH

needs_cc = pytest.mark.skipif(compiled_mod.compiler() is None, reason="no C compiler on this machine")


@pytest.fixture
def empty_cache(tmp_path, monkeypatch):
    """An empty compile cache, nothing loaded or pending; no quick tier (tests/solvers/test_quick_compile.py):
    what runs before gcc's build ends is the interpreter."""
    monkeypatch.setenv("GREYFIT_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setenv("GREYFIT_QUICK_COMPILER", "off")
    monkeypatch.setattr(compiled_mod, "_memory", {})
    monkeypatch.setattr(compiled_mod, "_pending", set())
    monkeypatch.setattr(compiled_mod, "_failed", {})
    return tmp_path


@pytest.fixture
def gated_cc(empty_cache, monkeypatch):
    """CC that runs gcc only once `gate` exists; an empty cache and nothing loaded or pending."""
    gate = empty_cache / "gate"
    cc = empty_cache / "gated-cc"
    cc.write_text(f"#!/bin/sh\nwhile [ ! -e {gate} ]; do sleep 0.02; done\nexec {compiled_mod.compiler()} \"$@\"\n")
    cc.chmod(cc.stat().st_mode | stat.S_IEXEC)
    monkeypatch.setenv("CC", str(cc))
    monkeypatch.setenv("GREYFIT_COMPILE", "auto")
    yield gate
    gate.touch()                          # let the builds still waiting end
    compiled_mod.wait_for_builds(60)


def _interpreted(monkeypatch, request):
    monkeypatch.setenv("GREYFIT_COMPILE", "never")
    result = fit_model(request)
    monkeypatch.setenv("GREYFIT_COMPILE", "auto")
    return result


def _summary(result) -> tuple:
    """What a fit answers, to the last bit (not how it ran: `compiled`, wall time)."""
    s = result.solver
    return (result.success, s.return_status, s.iterations, s.starts, s.starts_at_best, result.metrics.cost,
            {k: (p.value, p.stderr) for k, p in result.parameters.items()},
            [w.code for w in result.warnings], result.quality)


def _with_options(request, **options):
    return request.model_copy(update={"options": request.options.model_copy(update=options)})


@needs_cc
@pytest.mark.parametrize("method,n", [("multiple_shooting", 801), ("single_shooting", 201),
                                      ("single_shooting", 801)])
def test_compiled_kernels_give_the_interpreters_numbers_bit_for_bit(empty_cache, monkeypatch, method, n):
    """The claim the handover rests on (-ffp-contract=off): the same fit interpreted and compiled
    gives identical estimates, standard errors, cost and iterations. Single shooting at 201
    samples runs the mapped graph, at 801 the folded loops."""
    request = _request(method=method, n=n)
    monkeypatch.setenv("GREYFIT_COMPILE", "never")
    plain = fit_model(request)
    monkeypatch.setenv("GREYFIT_COMPILE", "always")
    fast = fit_model(request)
    assert plain.solver.compiled is False and fast.solver.compiled is True
    assert _summary(fast) == _summary(plain)


@needs_cc
def test_a_first_fit_does_not_wait_for_gcc(gated_cc, monkeypatch):
    """Work this large was compiled in the foreground (the fit waited for gcc); now the fit ends
    interpreted while gcc is held back, and the next fit after the build runs compiled, with the
    same answer bit for bit."""
    request = _request(n=4001)
    first = fit_model(request)
    assert first.solver.compiled is False
    assert compiled_mod.building_any()    # gcc is still held: the fit did not wait for it
    assert _summary(first) == _summary(_interpreted(monkeypatch, request))
    for name in ("c", "k"):
        assert first.parameters[name].value == pytest.approx(MSD_TRUTH[name], rel=0.02)
    gated_cc.touch()
    assert compiled_mod.wait_for_builds(120)
    again = fit_model(request)
    assert again.solver.compiled is True
    assert _summary(again) == _summary(first)


@needs_cc
@pytest.mark.parametrize("max_iter", [200, 3])
def test_a_build_that_ends_mid_solve_changes_nothing(gated_cc, monkeypatch, max_iter):
    """The compile ends while the first start's interpreted solve runs (released at its Ipopt call):
    that solve goes on interpreted to its own end, the next start begins on the compiled NLP, and
    the multistart's answer is the interpreted one bit for bit. An unconverged start stops at
    max_iter: nothing restarts it with a fresh max_iter."""
    request = _with_options(_request(n=801), multistart=3, max_iter=max_iter)
    real = solver_mod.run_ipopt
    calls, iterations = [], []

    def release_then_run(*args, **kwargs):
        if not calls:
            gated_cc.touch()
            assert compiled_mod.wait_for_builds(120)
        calls.append(args[0])
        out = real(*args, **kwargs)
        iterations.append(out.iterations)
        return out

    monkeypatch.setattr(solver_mod, "run_ipopt", release_then_run)
    moved = fit_model(request)
    monkeypatch.setattr(solver_mod, "run_ipopt", real)
    assert moved.solver.compiled is True
    assert calls[0] is not calls[1]     # the first start interpreted, the next ones compiled
    assert calls[2] is calls[1]
    assert max(iterations) <= max_iter
    assert _summary(moved) == _summary(_interpreted(monkeypatch, request))
    if max_iter == 3:
        assert moved.solver.return_status == "Maximum_Iterations_Exceeded"
        assert moved.solver.iterations == 3     # the best start, cut at max_iter
    else:
        assert moved.solver.return_status == "Solve_Succeeded"


@pytest.fixture
def quick_gated_cc(empty_cache, monkeypatch):
    """CC behind a gate that, once open, answers at once: each library was built before (by gcc, in
    a store keyed by its C source) and is copied. So a build ends a few ms after the gate opens,
    at a moment the test chooses, as on a machine where gcc happens to finish just then."""
    gate, store = empty_cache / "gate", empty_cache / "store"
    store.mkdir()
    cc = empty_cache / "quick-cc"
    cc.write_text(f"""#!/bin/sh
prev=""; src=""; out=""
for a in "$@"; do [ "$prev" = "-o" ] && out="$a"; case "$a" in *.c) src="$a";; esac; prev="$a"; done
kept="{store}/$(sha1sum "$src" | cut -c1-40).so"
while [ ! -e {gate} ]; do sleep 0.005; done
if [ -e "$kept" ]; then exec cp "$kept" "$out"; fi
{compiled_mod.compiler()} "$@" && cp "$out" "$kept"
""")
    cc.chmod(cc.stat().st_mode | stat.S_IEXEC)
    monkeypatch.setenv("CC", str(cc))
    monkeypatch.setenv("GREYFIT_COMPILE", "auto")
    yield gate
    gate.touch()
    compiled_mod.wait_for_builds(60)


def _forget_compiled(monkeypatch, cache):
    """A fresh process's view: nothing loaded, no NLP made, an empty disk cache (the quick
    compiler's store kept)."""
    monkeypatch.setenv("GREYFIT_CACHE_DIR", str(cache))
    monkeypatch.setattr(compiled_mod, "_memory", {})
    monkeypatch.setattr(compiled_mod, "_failed", {})
    monkeypatch.setattr(structured, "_SOLVERS", OrderedDict())


@needs_cc
def test_the_answer_does_not_depend_on_when_gcc_finishes(quick_gated_cc, empty_cache, monkeypatch):
    """gcc finishing at several moments of a single-start fit (before it, 0.02-0.25 s into its
    Ipopt solve, never): the same answer bit for bit. (The old mid-solve handover stopped Ipopt when
    the build ended and restarted it from that iterate with a fresh barrier and max_iter.)"""
    request = _request(n=4001, guess=(8.0, 0.3))     # 30 Ipopt iterations, ~0.5 s interpreted
    reference = _summary(_interpreted(monkeypatch, request))
    gate = quick_gated_cc
    gate.touch()                 # fills the store: from now on a build takes milliseconds
    first = fit_model(request)
    assert compiled_mod.wait_for_builds(120) and _summary(first) == reference
    warm = fit_model(request)
    assert warm.solver.compiled is True and _summary(warm) == reference
    for k, delay in enumerate((0.02, 0.1, 0.25)):
        gate.unlink()
        _forget_compiled(monkeypatch, empty_cache / f"cache{k}")
        moved = _fit_opening_gate_after(request, gate, delay, monkeypatch)
        assert compiled_mod.wait_for_builds(120)
        assert _summary(moved) == reference, delay


def _fit_opening_gate_after(request, gate, delay: float, monkeypatch):
    """`fit_model(request)`, the gate opened `delay` s into its first Ipopt solve."""
    real = solver_mod.run_ipopt
    timers: list[threading.Timer] = []

    def release_later(*args, **kwargs):
        if not timers:
            timers.append(threading.Timer(delay, gate.touch))
            timers[0].start()
        return real(*args, **kwargs)

    monkeypatch.setattr(solver_mod, "run_ipopt", release_later)
    try:
        return fit_model(request)
    finally:
        monkeypatch.setattr(solver_mod, "run_ipopt", real)
        for t in timers:
            t.join()
