"""`greyfit batch`: many fits locally in parallel, resumable."""
import json
import subprocess
import sys
from pathlib import Path

import pytest

from tests.service.conftest import msd_request

ROOT = Path(__file__).resolve().parents[1]


def run_batch(requests: Path, out: Path):
    return subprocess.run([sys.executable, "-m", "greyfit.service.cli", "batch", str(requests), "--out", str(out),
                           "--workers", "2"], cwd=ROOT, capture_output=True, text=True, timeout=300)


@pytest.mark.slow
def test_batch_runs_every_line_and_resumes(tmp_path):
    requests, out = tmp_path / "requests.jsonl", tmp_path / "results.jsonl"
    bad = msd_request(9)
    bad["experiments"][0]["time"][3] = 0.0
    requests.write_text("\n".join(json.dumps(b) for b in [msd_request(0), bad, msd_request(1)]) + "\n")
    proc = run_batch(requests, out)
    assert proc.returncode == 0, proc.stderr
    assert "3/3" in proc.stderr
    lines = [json.loads(x) for x in out.read_text().splitlines()]
    by_line = {r["line"]: r for r in lines}
    assert sorted(by_line) == [1, 2, 3]
    assert by_line[1]["status"] == by_line[3]["status"] == "succeeded"
    assert by_line[1]["result"]["parameters"]["k"]["value"] == pytest.approx(5.0, rel=0.02)
    assert by_line[2]["status"] == "failed" and by_line[2]["error"]["type"] == "DataError"
    assert "experiments[0].time" in by_line[2]["error"]["field"]

    # a re-run skips what is done and only fits the new lines (also a line with invalid JSON)
    with requests.open("a") as f:
        f.write(json.dumps(msd_request(2)) + "\n{broken\n")
    proc = run_batch(requests, out)
    assert proc.returncode == 0, proc.stderr
    assert "3 already done, 2 to do" in proc.stderr
    lines = [json.loads(x) for x in out.read_text().splitlines()]
    assert sorted(r["line"] for r in lines) == [1, 2, 3, 4, 5]
    assert {r["line"]: r["status"] for r in lines}[5] == "failed"
