"""The command line never looks hung: with an empty compile cache it prints its answer and exits,
handing the gcc builds still running to a detached process; Ctrl-C ends it with 130, one line and
no traceback; a reader that leaves (`| head`) costs no traceback either.

That the process does not wait for its builds is shown without a clock: when it has exited, the
libraries it handed over are not yet on disk; the detached process then builds every one of them
(and leaves no temporary file), and the next run finds them all and gives the same numbers.
"""
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from greyfit.solvers.dynamics import compiled
from tests.service.test_discover_api import duffing_body

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "msd_request.json"
HANDED = "go on in a detached process (pid "

needs_gcc = pytest.mark.skipif(compiled.compiler() is None, reason="no C compiler: nothing is built")


def cli(*args: str, cache: Path, **popen) -> subprocess.Popen:
    env = {**os.environ, "GREYFIT_CACHE_DIR": str(cache), "GREYFIT_COMPILE": "auto"}
    return subprocess.Popen([sys.executable, "-m", "greyfit.service.cli", *args], cwd=ROOT, env=env,
                            text=True, **popen)


def libraries(cache: Path) -> set[str]:
    return {p.name for p in (cache / "compiled").glob("*.so")}


def leftovers(cache: Path) -> list[str]:
    """Temporary build folders and hand-over files: none may stay."""
    folder = cache / "compiled"
    return [p.name for p in folder.iterdir() if p.is_dir() or p.name.startswith(".handover-")]


def ended(pid: int) -> bool:
    """Whether the process is gone or a zombie (the detached builder is not this test's child)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    except (FileNotFoundError, ProcessLookupError):
        return True


def wait_ended(pid: int, timeout: float = 240) -> None:
    deadline = time.monotonic() + timeout
    while not ended(pid):
        assert time.monotonic() < deadline, f"the detached builder {pid} still runs after {timeout} s"
        time.sleep(0.1)


@needs_gcc
def test_a_first_fit_prints_exits_and_leaves_its_builds_to_a_detached_process(tmp_path):
    proc = cli("fit", str(EXAMPLE), cache=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    out, err = proc.communicate(timeout=300)
    at_exit = libraries(tmp_path)
    assert proc.returncode == 0, err
    first = json.loads(out)
    assert abs(first["parameters"]["c"]["value"] - 0.8) < 0.01    # made with c = 0.8, k = 5.0
    line = next(x for x in err.splitlines() if HANDED in x)
    count, pid = int(line.split()[1]), int(line.split(HANDED)[1].split(")")[0])
    wait_ended(pid)
    handed = libraries(tmp_path) - at_exit
    assert count > 0 and len(handed) == count     # none was built when the CLI exited; all are now
    assert leftovers(tmp_path) == []

    again = cli("fit", str(EXAMPLE), cache=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    out, err = again.communicate(timeout=300)
    assert again.returncode == 0 and HANDED not in err           # everything was in the cache
    assert json.loads(out)["parameters"] == first["parameters"]  # compiled gives the same bits


@needs_gcc
def test_ctrl_c_exits_130_without_a_traceback(tmp_path):
    request = tmp_path / "duffing.json"
    request.write_text(json.dumps(duffing_body()))
    proc = cli("discover", str(request), cache=tmp_path / "cache", stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    first = proc.stderr.readline()          # the discovery has begun: the declared model is being fitted
    assert "fitting the declared model" in first
    deadline = time.monotonic() + 120
    while not list((tmp_path / "cache").glob("compiled/*.lock")):   # and a build with it
        assert time.monotonic() < deadline and proc.poll() is None
        time.sleep(0.01)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == 130
    assert err.strip().splitlines()[-1] == "greyfit: interrupted" and "Traceback" not in err
    assert out == ""
    assert leftovers(tmp_path / "cache") == []   # the builds begun were stopped and cleaned away


def test_a_reader_that_leaves_costs_no_traceback(tmp_path):
    proc = cli("fit", str(EXAMPLE), "--summary", cache=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    proc.stdout.close()                     # the reader has gone before the answer (`| true`, `| head` done)
    err = proc.stderr.read()
    assert proc.wait(timeout=300) == 141 and "Traceback" not in err and "Exception" not in err
    assert leftovers(tmp_path) == []
