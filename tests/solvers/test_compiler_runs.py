"""How gcc is run: its whole process tree ends at the time limit, a few compile at once, and a
source too large for -O3 is compiled at -O1 or not at all.

Defect behind these: `subprocess.run(timeout=...)` killed only gcc's driver, and its `cc1` ran on,
orphaned; a discovery run left a dozen of them (3 GB each) for half an hour beside the fits.
"""
import contextlib
import os
import subprocess
import sys
import threading
import time

import pytest

from greyfit.solvers.dynamics import compiled as compiled_mod


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split()[2] != "Z"
    except FileNotFoundError:
        return False


@pytest.mark.skipif(sys.platform != "linux", reason="reads /proc")
def test_a_compiler_past_its_time_limit_is_ended_with_its_children(tmp_path, monkeypatch):
    """A stand-in compiler that starts a child of its own (as gcc starts cc1) and hangs: at the limit
    both are gone, and the build says it failed."""
    pids = tmp_path / "pids"
    cc = tmp_path / "cc"
    cc.write_text(f"#!/bin/sh\nsleep 300 &\necho $! >> {pids}\necho $$ >> {pids}\nwait\n")
    cc.chmod(0o755)
    monkeypatch.setattr(compiled_mod, "COMPILE_TIMEOUT_S", 1)
    assert compiled_mod._run_compiler([str(cc)]) is False
    started = [int(p) for p in pids.read_text().split()]
    assert len(started) == 2
    deadline = time.monotonic() + 10
    while any(_alive(p) for p in started) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not any(_alive(p) for p in started), "the compiler's child outlived the time limit"


def test_compiles_queue_for_the_slots(tmp_path, monkeypatch):
    """With one slot, two builds never run the compiler at the same time."""
    monkeypatch.setenv("GREYFIT_COMPILE_SLOTS", "1")
    running, overlaps = tmp_path / "running", tmp_path / "overlaps"
    cc = tmp_path / "cc"
    cc.write_text(f"#!/bin/sh\nif [ -e {running} ]; then echo x >> {overlaps}; fi\ntouch {running}\n"
                  f"sleep 0.3\nrm -f {running}\n")
    cc.chmod(0o755)

    def one():
        with compiled_mod._compile_slot(tmp_path):
            subprocess.run([str(cc)], check=True)
    threads = [threading.Thread(target=one) for _ in range(3)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    assert not overlaps.exists()


def test_the_slots_default_to_half_the_cpus(monkeypatch):
    monkeypatch.delenv("GREYFIT_COMPILE_SLOTS", raising=False)
    assert compiled_mod.compile_slots() == max(1, (os.cpu_count() or 2) // 2)
    monkeypatch.setenv("GREYFIT_COMPILE_SLOTS", "3")
    assert compiled_mod.compile_slots() == 3
    for typo in ("two", "0", "1.5"):   # the default, and said (it went unseen)
        monkeypatch.setenv("GREYFIT_COMPILE_SLOTS", typo)
        with pytest.warns(RuntimeWarning, match=f"GREYFIT_COMPILE_SLOTS='{typo}'"):
            assert compiled_mod.compile_slots() == max(1, (os.cpu_count() or 2) // 2)


def test_large_sources_compile_at_o1_and_huge_ones_not_at_all():
    assert compiled_mod.optimisation_flags(200_000) == ["-O3"]
    assert compiled_mod.optimisation_flags(3_000_000) == ["-O1"]
    assert compiled_mod.optimisation_flags(12_000_000) is None


_EXITS_WHILE_BUILDING = """
import pathlib, sys, time
import casadi as ca
from greyfit.solvers.dynamics import compiled
x = ca.SX.sym("x", 3)
assert compiled.library(ca.Function("exits_while_building", [x], [ca.sin(x) * x])) is None   # background
started = pathlib.Path(sys.argv[1])
deadline = time.monotonic() + 60
while time.monotonic() < deadline:   # the compiler runs, and has written both its pids
    if started.exists() and len(started.read_text().split()) >= 2:
        break
    time.sleep(0.02)
sys.exit(0)   # the fit has returned, the script ends
"""


@pytest.mark.skipif(sys.platform != "linux", reason="reads /proc")
def test_a_process_that_exits_takes_its_background_compilers_with_it(tmp_path):
    """A script whose fit has returned while a library is still compiling ends, and the compiler
    (here a stand-in that starts a child, as gcc starts cc1, and hangs) ends with it: its output
    would go to a temporary folder removed at exit, and left running it took a core from the next
    process's first fit. (Before: it ran on under `timeout` for up to COMPILE_TIMEOUT_S.)"""
    pids = tmp_path / "pids"
    cc = tmp_path / "cc"
    cc.write_text(f"#!/bin/sh\nsleep 300 &\necho $! >> {pids}\necho $$ >> {pids}\nwait\n")
    cc.chmod(0o755)
    env = {**os.environ, "CC": str(cc), "GREYFIT_COMPILE": "auto", "GREYFIT_CACHE_DIR": str(tmp_path / "cache")}
    done = subprocess.run([sys.executable, "-c", _EXITS_WHILE_BUILDING, str(pids)], env=env,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    started = [int(p) for p in pids.read_text().split()]
    assert len(started) == 2, started
    deadline = time.monotonic() + 10
    while any(_alive(p) for p in started) and time.monotonic() < deadline:
        time.sleep(0.05)
    alive = [p for p in started if _alive(p)]
    for p in alive:   # (the old behaviour: leave nothing running after the test)
        with contextlib.suppress(ProcessLookupError):
            os.kill(p, 9)
    assert not alive, "a compiler outlived the process that started it"
