"""The heap a fit keeps (solvers/dynamics/heap.py): glibc's thresholds are set once per process, so a
fit's arrays of a few MB come from the heap the last fit freed instead of fresh `mmap`s."""
from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest

glibc = pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc",
                           reason="the thresholds are glibc's")

# Where does a 16 MB array live after the first fit? glibc's program break (sbrk(0)) bounds the heap;
# an allocation above its threshold is an mmap far above it.
PROBE = """
import ctypes, numpy as np
import greyfit
from tests.systems import msd_experiment, msd_model, simulate_msd
t = np.linspace(0, 10, 101)
req = greyfit.FitRequest.model_validate({"model": msd_model(c=0.5, k=3.0), "method": "equation_error",
                                         "experiments": [msd_experiment(t, simulate_msd(t), noise=0.005, seed=1)]})
greyfit.fit(req)
libc = ctypes.CDLL(None)
libc.sbrk.restype = ctypes.c_void_p
a = np.ones(2 * 2 ** 20)   # 16 MB
print(int(a.ctypes.data < libc.sbrk(0)))
"""


def _heap_allocated(env: dict[str, str]) -> bool:
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    out = subprocess.run([sys.executable, "-c", PROBE], env={**os.environ, "GREYFIT_COMPILE": "never", **env},
                         capture_output=True, text=True, timeout=300, cwd=root, check=True)
    return out.stdout.strip().splitlines()[-1] == "1"


@glibc
def test_after_a_fit_arrays_of_a_few_megabytes_come_from_the_kept_heap():
    assert _heap_allocated({}) is True


@glibc
def test_greyfit_heap_system_leaves_glibcs_defaults():
    # glibc's default: the first 16 MB request is an mmap of its own (its threshold starts at 128 KB)
    assert _heap_allocated({"GREYFIT_HEAP": "system"}) is False


@glibc
def test_an_unknown_heap_setting_is_said_and_the_heap_kept(monkeypatch):
    from greyfit.solvers.dynamics import heap
    monkeypatch.setattr(heap, "_done", False)
    monkeypatch.setattr(heap, "_kept", False)
    monkeypatch.setenv("GREYFIT_HEAP", "sytem")
    with pytest.warns(RuntimeWarning, match="GREYFIT_HEAP='sytem' is not one of kept, system"):
        assert heap.keep_heap() is True
