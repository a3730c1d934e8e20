"""Cold start: the first fit of a new structure interprets while gcc compiles, and moves to the
compiled NLP mid-solve once the libraries exist (solvers/methods/shooting/handover.py).

The compiler is real gcc behind a gate (a wrapper that waits for a file), so a test decides when a
compile may finish; truth is the simulated record and the interpreted fit of the same request.
"""
import stat

import pytest

from greyfit.solvers.dynamics import compiled as compiled_mod
from greyfit.solvers.fit import fit_model
from greyfit.solvers.nlp import solver as solver_mod
from tests.solvers.test_compiled import _request
from tests.systems import MSD_TRUTH

needs_cc = pytest.mark.skipif(compiled_mod.compiler() is None, reason="no C compiler on this machine")


@pytest.fixture
def gated_cc(tmp_path, monkeypatch):
    """CC that runs gcc only once `gate` exists; an empty cache and nothing loaded or pending."""
    gate = tmp_path / "gate"
    cc = tmp_path / "gated-cc"
    cc.write_text(f"#!/bin/sh\nwhile [ ! -e {gate} ]; do sleep 0.02; done\nexec {compiled_mod.compiler()} \"$@\"\n")
    cc.chmod(cc.stat().st_mode | stat.S_IEXEC)
    monkeypatch.setenv("CC", str(cc))
    monkeypatch.setenv("GREYFIT_CACHE_DIR", str(tmp_path / "cache"))
    monkeypatch.setenv("GREYFIT_COMPILE", "auto")
    monkeypatch.setattr(compiled_mod, "_memory", {})
    monkeypatch.setattr(compiled_mod, "_pending", set())
    monkeypatch.setattr(compiled_mod, "_failed", {})
    yield gate
    gate.touch()                          # let the builds still waiting end
    compiled_mod.wait_for_builds(60)


def _interpreted(monkeypatch, request):
    monkeypatch.setenv("GREYFIT_COMPILE", "never")
    result = fit_model(request)
    monkeypatch.setenv("GREYFIT_COMPILE", "auto")
    return result


def _assert_same_fit(a, b, rel=1e-6):
    for name in ("c", "k"):
        assert a.parameters[name].value == pytest.approx(b.parameters[name].value, rel=rel)
        assert a.parameters[name].value == pytest.approx(MSD_TRUTH[name], rel=0.02)


@needs_cc
def test_a_first_fit_does_not_wait_for_gcc(gated_cc, monkeypatch):
    """Work this large was compiled in the foreground (the fit waited for gcc); now the fit ends
    interpreted while gcc is held back, and the next fit after the build runs compiled."""
    request = _request(n=4001)
    first = fit_model(request)
    assert first.solver.compiled is False
    assert compiled_mod.building_any()    # gcc is still held: the fit did not wait for it
    _assert_same_fit(first, _interpreted(monkeypatch, request))
    gated_cc.touch()
    assert compiled_mod.wait_for_builds(120)
    again = fit_model(request)
    assert again.solver.compiled is True
    _assert_same_fit(again, first)


@needs_cc
def test_the_solve_moves_to_compiled_code_when_the_libraries_arrive(gated_cc, monkeypatch):
    """The compile ends while the interpreted solve runs (released at its first Ipopt call): Ipopt
    stops at the next iteration and the compiled NLP goes on from there to the same optimum."""
    request = _request(n=4001)
    real = solver_mod.run_ipopt
    calls = []

    def release_then_run(*args, **kwargs):
        if not calls:
            gated_cc.touch()
            assert compiled_mod.wait_for_builds(120)
        calls.append(args[0])
        return real(*args, **kwargs)

    monkeypatch.setattr(solver_mod, "run_ipopt", release_then_run)
    moved = fit_model(request)
    monkeypatch.setattr(solver_mod, "run_ipopt", real)
    assert moved.solver.compiled is True
    assert len(calls) >= 2 and calls[0] is not calls[1]     # the interpreted NLP, then the compiled one
    assert moved.solver.return_status == "Solve_Succeeded"
    _assert_same_fit(moved, _interpreted(monkeypatch, request))
