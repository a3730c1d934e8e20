"""The lint gate (scripts/lint.sh, run by the test command before pytest) fails on each kind of
violation it exists for: a ruff finding, a type error, an import back up the layers."""
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
BIN = Path(sys.executable).parent
pytestmark = pytest.mark.skipif(not (BIN / "ruff").exists() or not (BIN / "lint-imports").exists(),
                                reason="the lint tools are installed by the test extra")


@pytest.fixture(scope="module")
def tree(tmp_path_factory):
    """A copy of what the gate reads (sources, configuration, the script, mypy's cache)."""
    root = tmp_path_factory.mktemp("gate")
    for name in ("schemas", "solvers", "service", "greyfit", "scripts", "tests", "bench"):
        shutil.copytree(ROOT / name, root / name, ignore=shutil.ignore_patterns("__pycache__"))
    for name in ("pyproject.toml",):
        shutil.copy(ROOT / name, root / name)
    if (ROOT / "build" / "mypy_cache").exists():
        shutil.copytree(ROOT / "build" / "mypy_cache", root / "build" / "mypy_cache")
    return root


def gate(root: Path) -> subprocess.CompletedProcess:
    return subprocess.run(["bash", str(root / "scripts" / "lint.sh"), sys.executable], cwd=root,
                          capture_output=True, text=True, timeout=600)


def test_the_tree_as_committed_passes(tree):
    proc = gate(tree)
    assert proc.returncode == 0, proc.stdout + proc.stderr


@pytest.mark.parametrize("where, text, tool", [
    ("solvers/methods/batch.py", "\nimport os\n", "ruff"),                     # unused import
    ("solvers/inference/statistics.py", "\n\ndef _bad() -> int:\n    return 'text'\n", "mypy"),
    ("solvers/inference/statistics.py", "\n\ndef _up():\n    from greyfit.service.http import app\n    return app\n",
     "import-linter"),                                                         # solvers -> service
])
def test_a_violation_fails_the_gate(tree, where, text, tool):
    path = tree / where
    original = path.read_text()
    try:
        path.write_text(original + text)
        proc = gate(tree)
    finally:
        path.write_text(original)
    assert proc.returncode != 0
    out = proc.stdout + proc.stderr
    last = [line for line in out.splitlines() if line.startswith("lint: ")][-1]
    assert last.startswith(f"lint: {tool}"), out[-2000:]
