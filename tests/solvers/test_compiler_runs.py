"""How gcc is run: its whole process tree ends at the time limit, a few compile at once, and a
source too large for -O3 is compiled at -O1 or not at all.

Defect behind these: `subprocess.run(timeout=...)` killed only gcc's driver, and its `cc1` ran on,
orphaned; a discovery run left a dozen of them (3 GB each) for half an hour beside the fits.
"""
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


def test_large_sources_compile_at_o1_and_huge_ones_not_at_all():
    assert compiled_mod.optimisation_flags(200_000) == ["-O3"]
    assert compiled_mod.optimisation_flags(3_000_000) == ["-O1"]
    assert compiled_mod.optimisation_flags(12_000_000) is None
