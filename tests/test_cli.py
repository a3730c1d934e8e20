"""`greyfit fit` as a user runs it: result JSON on stdout, clear message and exit 2 on bad input."""
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
EXAMPLE = ROOT / "examples" / "msd_request.json"


def run_cli(*args, stdin=None):
    return subprocess.run([sys.executable, "-m", "greyfit.service.cli", *args], cwd=ROOT, input=stdin,
                          capture_output=True, text=True, timeout=300)


def test_fit_prints_result_json():
    proc = run_cli("fit", str(EXAMPLE))
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout)
    assert result["success"] is True
    # the example was made with c = 0.8, k = 5.0 (tests/systems.py)
    assert result["parameters"]["c"]["value"] == pytest.approx(0.8, rel=0.03)
    assert result["parameters"]["k"]["value"] == pytest.approx(5.0, rel=0.01)


def test_fit_reads_stdin_and_reports_bad_input(tmp_path):
    body = json.loads(EXAMPLE.read_text())
    body["model"]["equations"]["v"] = "(u - c*v - kk*x)/m"
    proc = run_cli("fit", "-", stdin=json.dumps(body))
    assert proc.returncode == 2
    assert "ModelDefinitionError: equations.v: unknown name 'kk'" in proc.stderr
    body["model"]["equations"]["v"] = "(u - c*v - k*x)/m"
    body["experiments"][0]["time"] = body["experiments"][0]["time"][:-1]
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(body))
    proc = run_cli("fit", str(bad))
    assert proc.returncode == 2 and "time has 200" in proc.stderr
    proc = run_cli("fit", str(tmp_path / "missing.json"))
    assert proc.returncode == 2 and "no such file" in proc.stderr
    bad.write_text("{not json")
    proc = run_cli("fit", str(bad))
    assert proc.returncode == 2 and "not valid JSON" in proc.stderr
    bad.write_text('{"model": {}, "model": {}}')   # a key twice is refused, as over HTTP (read as text here)
    proc = run_cli("fit", str(bad))
    assert proc.returncode == 2 and "duplicate key 'model' in one object" in proc.stderr


def test_report_takes_o_for_its_directory_as_the_other_commands_do(tmp_path):
    """`greyfit report ... -o DIR` failed with "the following arguments are required: --out"."""
    pytest.importorskip("matplotlib")
    result = tmp_path / "result.json"
    assert run_cli("fit", str(EXAMPLE), "-o", str(result)).returncode == 0
    proc = run_cli("report", str(result), "--request", str(EXAMPLE), "-o", str(tmp_path / "figures"),
                   "--formats", "png")
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "figures" / "report.html").is_file() and str(tmp_path / "figures" / "report.html") in proc.stdout
    from greyfit.service.cli.commands import build_parser
    assert build_parser().parse_args(["report", "r.json", "--out", "d"]).out == "d"   # --out still works
    proc = run_cli("report", str(result))
    assert proc.returncode == 2 and "-o/--out" in proc.stderr


@pytest.mark.parametrize("name, value, says", [
    ("GREYFIT_COMPILE", "nevr", "GREYFIT_COMPILE: Input should be 'auto', 'always' or 'never'"),
    ("GREYFIT_HEAP", "sytem", "GREYFIT_HEAP: Input should be 'kept' or 'system'"),
    ("GREYFIT_WORKERS", "0", "GREYFIT_WORKERS: Input should be greater than or equal to 1"),
    ("GREYFIT_QUICK_COMPILER", "/no/such/tcc",
     "GREYFIT_QUICK_COMPILER: Value error, '/no/such/tcc' is not a program on PATH nor a path to one")])
def test_serve_refuses_a_setting_it_does_not_know_and_names_the_variable(tmp_path, name, value, says):
    """A typo in the environment stops the service at start, naming the variable and the values it
    takes (GREYFIT_COMPILE and GREYFIT_HEAP were read by the numerics alone, which took any unknown
    value as the default without a word)."""
    env = {**os.environ, "GREYFIT_DATA_DIR": str(tmp_path), name: value}
    proc = subprocess.run([sys.executable, "-m", "greyfit.service.cli", "serve", "--port", "0"], cwd=ROOT,
                          env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert "invalid setting in the environment" in proc.stderr and says in proc.stderr, proc.stderr


def test_the_library_says_when_it_does_not_know_a_compile_setting(monkeypatch):
    from greyfit.solvers.dynamics import compiled
    monkeypatch.setenv("GREYFIT_COMPILE", "allways")
    with pytest.warns(RuntimeWarning, match="GREYFIT_COMPILE='allways' is not one of auto, always, never"):
        assert compiled.mode() == "auto"
    monkeypatch.setenv("GREYFIT_COMPILE", "Never")   # case and spaces do not matter
    assert compiled.mode() == "never"
