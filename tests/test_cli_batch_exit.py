"""`greyfit batch` says by its exit code whether anything worked."""
import json
import subprocess
import sys
from pathlib import Path

from tests.service.conftest import msd_request

ROOT = Path(__file__).resolve().parents[1]


def test_batch_exits_1_when_every_request_failed(tmp_path):
    requests, out = tmp_path / "requests.jsonl", tmp_path / "results.jsonl"
    bad = msd_request(0, n=21)
    bad["model"]["equations"]["v"] = "(u - c*v - kk*x)/m"
    requests.write_text(json.dumps(bad) + "\n{broken\n")
    proc = subprocess.run([sys.executable, "-m", "greyfit.service.cli", "batch", str(requests), "--out", str(out),
                           "--workers", "1"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 1, proc.stderr
    assert "all 2 requests failed" in proc.stderr
    assert [json.loads(x)["status"] for x in out.read_text().splitlines()] == ["failed", "failed"]
