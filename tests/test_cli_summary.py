"""`greyfit fit|simulate --summary`, `--fail-on` and `--version` as a user runs them.

The example (examples/msd_request.json) was simulated with c = 0.8 N s/m, k = 5.0 N/m (m = 2 known)
and measured with noise: the printed report must give those back, agree with the JSON result, and
carry the declared units.
"""
import difflib
import json
import re
from decimal import Decimal
from importlib.metadata import version

import pytest

from tests.test_cli import EXAMPLE, ROOT, run_cli

TRUTH = {"c": 0.8, "k": 5.0}
UNITS = {"c": "N s/m", "k": "N/m"}
NUMBER = r"[-+]?\d+(?:\.\d+)?(?:e[-+]?\d+)?"
ROW = re.compile(rf"^\s+(\w+)\s+({NUMBER})\s+({NUMBER})\s+({NUMBER}) %\s+\[({NUMBER}), ({NUMBER})\]\s+(.*?)\s+"
                 rf"({NUMBER})\s*$")


def section(report: str, name: str) -> list[str]:
    lines = report.splitlines()
    start = lines.index(next(line for line in lines if line.startswith(f"[[{name}]]")))
    end = next((i for i in range(start + 1, len(lines)) if lines[i].startswith("[[")), len(lines))
    return lines[start + 1:end]


def parameter_rows(report: str) -> dict[str, dict]:
    rows = {}
    for line in section(report, "Parameters"):
        m = ROW.match(line)
        if m:
            name, value, stderr, rel, lo, hi, unit, initial = m.groups()
            rows[name] = {"value": float(value), "stderr": float(stderr), "rel": float(rel),
                          "ci": (float(lo), float(hi)), "unit": unit, "initial": float(initial)}
    return rows


@pytest.fixture(scope="module")
def summary(tmp_path_factory):
    out = tmp_path_factory.mktemp("summary") / "result.json"
    proc = run_cli("fit", str(EXAMPLE), "--summary", "-o", str(out))
    assert proc.returncode == 0, proc.stderr
    return proc.stdout, json.loads(out.read_text())


def test_summary_gives_the_true_parameters_with_units(summary):
    report, _ = summary
    rows = parameter_rows(report)
    assert set(rows) == {"c", "k"}, report   # m is fixed: its row has no stderr or CI
    for name, truth in TRUTH.items():
        row = rows[name]
        assert row["value"] == pytest.approx(truth, rel=0.01), (name, row)
        # the truth inside the printed 95 % interval, and the interval a few stderr wide
        assert row["ci"][0] < truth < row["ci"][1], (name, row)
        assert 2.5 < (row["ci"][1] - row["ci"][0]) / row["stderr"] < 5.0, (name, row)
        assert row["unit"] == UNITS[name]
    assert rows["c"]["initial"] == 0.3 and rows["k"]["initial"] == 2.0
    assert re.search(r"^\s+m\s+2\s+2\s+fixed$", report, re.M), report
    assert "verdict:      converged; quality good" in report
    assert section(report, "Warnings") == ["    none"]


def test_summary_numbers_are_the_json_result(summary):
    report, result = summary
    rows = parameter_rows(report)
    for name, row in rows.items():
        p = result["parameters"][name]
        assert row["value"] == pytest.approx(p["value"], rel=1e-5)
        assert row["stderr"] == pytest.approx(p["stderr"], rel=5e-3)
        assert row["ci"] == pytest.approx(tuple(p["ci95"]), rel=1e-5)
        assert row["rel"] == pytest.approx(100 * p["stderr"] / p["value"], abs=0.006)
        assert p["unit"] == row["unit"]
    outputs = {}
    for line in section(report, "Outputs")[1:]:
        name, records, fit, nrmse, rmse, *_ = line.split()
        outputs[(name, records)] = (float(fit), float(nrmse), float(rmse))
    assert set(outputs) == {("x", "estimation"), ("v", "estimation")}
    for (name, _), (fit, nrmse, rmse) in outputs.items():
        assert fit == pytest.approx(result["metrics"]["fit_percent"][name], abs=0.006)
        assert nrmse == pytest.approx(1 - result["metrics"]["fit_percent"][name] / 100, abs=6e-5)
        assert rmse == pytest.approx(result["metrics"]["rmse"][name], rel=1e-3)
        assert fit > 95   # the example's noise allows about 98 %
    assert f"data points:  {result['metrics']['ndata']}" in report


def documented_summary() -> str:
    """The text block docs/cli.md shows under `greyfit fit examples/msd_request.json --summary`."""
    page = (ROOT / "docs" / "cli.md").read_text(encoding="utf-8")
    after = page[page.index("`greyfit fit examples/msd_request.json --summary` prints"):]
    return re.search(r"```text\n(.*?)```", after, re.S).group(1)


def without_timing(report: str) -> str:
    """The solver line's wall time and the time line's stages are what differs from run to run."""
    report = re.sub(r"^(    solver: .*), \d+\.\d+ s$", r"\1, <time> s", report, flags=re.M)
    return re.sub(r"^(    time: +)\d.*$", r"\1<stages>", report, flags=re.M)


def same_report(shown: str, printed: str) -> bool:
    """Equal text; equal integers; decimals within one unit of the last digit shown (the solver's last
    bits may differ between machines' BLAS)."""
    token = re.compile(rf"({NUMBER})")
    a, b = token.split(shown), token.split(printed)
    if len(a) != len(b):
        return False
    for i, (x, y) in enumerate(zip(a, b)):
        if i % 2 == 0 or "." not in x + y:
            if x != y:
                return False
        elif abs(Decimal(x) - Decimal(y)) > Decimal(1).scaleb(Decimal(x).as_tuple().exponent):
            return False
    return True


def test_the_summary_in_the_docs_is_what_the_command_prints():
    proc = run_cli("fit", "examples/msd_request.json", "--summary")
    assert proc.returncode == 0, proc.stderr
    shown, printed = without_timing(documented_summary()), without_timing(proc.stdout)
    assert "<time> s" in shown and "<time> s" in printed
    assert "<stages>" in shown and "<stages>" in printed
    assert same_report(shown, printed), "docs/cli.md shows another report than the command prints:\n" + "".join(
        difflib.unified_diff(shown.splitlines(True), printed.splitlines(True), "docs/cli.md", "printed"))


def test_the_result_carries_its_model_so_simulate_needs_only_the_records(summary, tmp_path):
    _, result = summary
    assert result["model"]["equations"] == json.loads(EXAMPLE.read_text())["model"]["equations"]
    (tmp_path / "result.json").write_text(json.dumps(result))
    proc = run_cli("simulate", str(EXAMPLE), "--result", str(tmp_path / "result.json"), "--summary")
    assert proc.returncode == 0, proc.stderr
    rows = {line.split()[0]: line.split()[1:] for line in section(proc.stdout, "Against the measured outputs")[1:]}
    for name in ("x", "v"):   # the same estimates and initial states: the fit's own simulation
        assert float(rows[name][0]) == pytest.approx(result["metrics"]["fit_percent"][name], abs=0.05)
    used = {line.split()[0]: float(line.split()[1]) for line in section(proc.stdout, "Parameters used")[1:]}
    assert used["c"] == pytest.approx(result["parameters"]["c"]["value"], rel=1e-5)


def test_version():
    proc = run_cli("--version")
    assert proc.returncode == 0
    assert proc.stdout.strip() == f"greyfit {version('greyfit')}"


def variant(tmp_path, name: str, change) -> str:
    body = json.loads(EXAMPLE.read_text())
    change(body)
    path = tmp_path / f"{name}.json"
    path.write_text(json.dumps(body))
    return str(path)


def stop_early(body):
    body.setdefault("options", {})["max_iter"] = 1   # Ipopt stops: not converged, quality failed


def product_of_dampings(body):
    # c and c2 enter only as their product: converged, but not identifiable (suspect)
    body["model"]["parameters"].append({"name": "c2", "value": 1.0, "lower": 0.1})
    body["model"]["equations"]["v"] = "(u - c*c2*v - k*x)/m"


@pytest.mark.parametrize("change,quality,codes", [(stop_early, "failed", {0: 0, "failed": 3, "suspect": 3}),
                                                  (product_of_dampings, "suspect", {0: 0, "failed": 0, "suspect": 3})])
def test_fail_on_exits_3_for_the_qualities_it_names(tmp_path, change, quality, codes):
    path = variant(tmp_path, quality, change)
    for fail_on, code in codes.items():
        args = ("fit", path) + (("--fail-on", fail_on) if fail_on else ())
        proc = run_cli(*args)
        assert proc.returncode == code, (fail_on, proc.stderr)
        assert json.loads(proc.stdout)["quality"] == quality   # the result is printed all the same
        if code == 3:
            assert f"the result is {quality} (--fail-on {fail_on})" in proc.stderr


def test_fail_on_leaves_a_good_fit_alone():
    proc = run_cli("fit", str(EXAMPLE), "--fail-on", "suspect")
    assert proc.returncode == 0, proc.stderr
    assert json.loads(proc.stdout)["quality"] == "good"


def test_every_option_has_help_text():
    from greyfit.service.cli.commands import build_parser
    parser = build_parser()
    subparsers = next(a for a in parser._actions if a.dest == "command")
    assert set(subparsers.choices) == {"fit", "discover", "serve", "batch", "simulate", "report", "design", "keys"}
    for name, sub in subparsers.choices.items():
        assert sub.description, name
        for action in sub._actions:
            assert action.help, f"greyfit {name} {action.option_strings or action.dest} has no help text"


def test_batch_fail_on_exits_3_when_a_result_is_failed(tmp_path):
    good = json.loads(EXAMPLE.read_text())
    stopped = json.loads(EXAMPLE.read_text())
    stop_early(stopped)
    requests, out = tmp_path / "requests.jsonl", tmp_path / "results.jsonl"
    requests.write_text(json.dumps(good) + "\n" + json.dumps(stopped) + "\n")
    proc = run_cli("batch", str(requests), "--out", str(out), "--workers", "1", "--fail-on", "failed")
    assert proc.returncode == 3, proc.stderr   # without --fail-on: 0 (tests/test_cli_batch.py)
    assert "1 result(s) are failed or worse (--fail-on failed)" in proc.stderr
    lines = sorted((json.loads(x) for x in out.read_text().splitlines()), key=lambda r: r["line"])
    assert [r["result"]["quality"] for r in lines] == ["good", "failed"]
