"""The compiled-function caches are bounded: least recently used out of memory, oldest off the disk.

Defect: each distinct model structure grew the process by ~93 KB (its loaded library) and the disk
cache by its library, never given back; the sample loops' own handles on the libraries (ctypes, in
solvers/dynamics/columns.py) were kept for ever too."""
import gc
from collections import OrderedDict
from pathlib import Path

import casadi as ca
import numpy as np
import pytest

from greyfit.solvers.dynamics import columns as columns_mod
from greyfit.solvers.dynamics import compiled as compiled_mod

needs_cc = pytest.mark.skipif(compiled_mod.compiler() is None, reason="no C compiler on this machine")


def structure(i: int) -> ca.Function:
    """A distinct expression graph per i (its constant is part of the graph, so of the cache key)."""
    x = ca.SX.sym("x", 2)
    return ca.Function(f"bound{i}", [x], [ca.vertcat(ca.sin(x[0]) * (i + 1.5), x[1] ** 2 + i)])


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("GREYFIT_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv("GREYFIT_COMPILE", "always")
    monkeypatch.setattr(compiled_mod, "_memory", {})
    return tmp_path / "compiled"


@needs_cc
def test_loaded_functions_are_bounded_least_recently_used_first(cache, monkeypatch):
    monkeypatch.setenv("GREYFIT_COMPILED_IN_MEMORY", "2")
    fns = [structure(i) for i in range(4)]
    for fn in fns[:2]:
        assert compiled_mod.compiled(fn)[1]
    assert compiled_mod.loaded(fns[0]) is not None        # used again: now the most recent
    for fn in fns[2:]:
        assert compiled_mod.compiled(fn)[1]
    assert len(compiled_mod._memory) == 2
    assert compiled_mod.loaded(fns[3]) is not None and compiled_mod.loaded(fns[1]) is None
    point = np.array([0.3, -1.2])
    again, is_compiled = compiled_mod.compiled(fns[1])    # dropped: loaded again from disk, same values
    assert is_compiled
    np.testing.assert_allclose(np.asarray(again(point)).ravel(), np.asarray(fns[1](point)).ravel(), rtol=1e-12)


@needs_cc
def test_the_disk_cache_deletes_its_oldest_libraries_past_its_size(cache, monkeypatch):
    assert compiled_mod.compiled(structure(0))[1]
    size = next(cache.glob("*.so")).stat().st_size
    monkeypatch.setenv("GREYFIT_CACHE_MAX_BYTES", str(int(size * 2.5)))   # room for two libraries
    monkeypatch.setattr(compiled_mod, "KEEP_RECENT_S", 0.0)
    for i in range(1, 5):
        assert compiled_mod.compiled(structure(i))[1]
    libraries = sorted(cache.glob("*.so"))
    assert len(libraries) == 2 and sum(p.stat().st_size for p in libraries) <= size * 2.5
    assert {p.name.split("_")[0] for p in libraries} == {"bound3", "bound4"}   # the newest kept
    monkeypatch.setattr(compiled_mod, "KEEP_RECENT_S", 600.0)       # a library built just now is never deleted
    assert compiled_mod.compiled(structure(5))[1] and len(list(cache.glob("*.so"))) == 3


def mapped(path: Path) -> bool:
    """Whether this process has the file mapped (a loaded, not yet closed library)."""
    return str(path) in Path("/proc/self/maps").read_text()


@needs_cc
@pytest.mark.skipif(not Path("/proc/self/maps").exists(), reason="no /proc/self/maps (not Linux)")
def test_the_sample_loops_libraries_are_bounded_and_closed_only_when_no_loop_uses_them(cache, monkeypatch):
    monkeypatch.setenv("GREYFIT_COMPILED_IN_MEMORY", "2")
    monkeypatch.setattr(columns_mod, "_libraries", OrderedDict())
    fns = [structure(10 + i) for i in range(4)]
    paths = [compiled_mod.library(fn) for fn in fns]
    point = np.array([[0.3, 0.1], [-1.2, 0.4]])            # two samples
    expected = np.asarray(fns[0].map(2)(point))
    held = columns_mod.Columns(fns[0])
    others = [columns_mod.Columns(fn) for fn in fns[1:]]
    assert held.compiled and all(c.compiled for c in others)
    assert list(columns_mod._libraries) == [str(p) for p in paths[2:]]   # the two most recent
    # out of the table, yet its Columns lives: still loaded, and it still computes
    assert mapped(paths[0]) and mapped(paths[1])
    np.testing.assert_allclose(held(point, n=2)[0], expected, rtol=1e-12)
    del others
    gc.collect()
    assert not mapped(paths[1])                              # out of the table and unused: closed
    assert mapped(paths[2]) and mapped(paths[3])             # in the table: kept for the next fit
    again = columns_mod.Columns(fns[0])     # the open library comes back into the table (no second load)
    assert list(columns_mod._libraries) == [str(paths[3]), str(paths[0])]
    gc.collect()
    assert not mapped(paths[2])                              # pushed out by it, and unused: closed
    del held, again
    gc.collect()
    assert mapped(paths[0])                                  # unused, but in the table
    for fn in fns[1:3]:                                      # two more structures push it out
        columns_mod.Columns(fn)
    gc.collect()
    assert not mapped(paths[0]) and not mapped(paths[3]) and mapped(paths[1]) and mapped(paths[2])
