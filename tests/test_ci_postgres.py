"""CI's PostgreSQL step (scripts/ci_postgres.sh, sourced by .ci/run), run for real on each of its paths.

The failing path is driven by a port where nothing listens and a configuration directory naming a
version that does not exist, so the start it attempts touches no real cluster; the machine's own
server is never stopped.
"""
import os
import socket
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "scripts" / "ci_postgres.sh"


def closed_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]     # free once the socket is closed: nothing answers there


def run(command: str, **env: str) -> subprocess.CompletedProcess:
    base = {k: v for k, v in os.environ.items() if not k.startswith("GREYFIT_")}
    return subprocess.run(["bash", "-c", command], cwd=ROOT, env={**base, **env}, capture_output=True,
                          text=True, timeout=60)


def test_ci_run_sources_the_postgres_step_before_the_tests():
    text = (ROOT / ".ci" / "run").read_text()
    assert text.index("source scripts/ci_postgres.sh") < text.index("scripts/test.sh")
    assert "set -euo pipefail" in text      # its `exit 1` ends the run


def test_installed_but_unreachable_fails_with_a_clear_message(tmp_path):
    (tmp_path / "99").mkdir()               # "installed": a version directory (no such cluster)
    port = closed_port()
    done = run(f"source {SCRIPT}; echo tests-would-run", GREYFIT_CI_PG_PORT=str(port),
               GREYFIT_CI_PG_CONF_DIR=str(tmp_path), GREYFIT_CI_PG_WAIT_SECONDS="1")
    assert done.returncode == 1, done
    assert "tests-would-run" not in done.stdout
    assert f"not answering on 127.0.0.1:{port}; starting it" in done.stderr
    assert f"ci: FAILED: PostgreSQL is installed here but no server answers on 127.0.0.1:{port}" in done.stderr
    assert "set GREYFIT_TEST_DATABASE_URL to a reachable server" in done.stderr


def test_not_installed_says_the_postgres_tests_will_be_skipped(tmp_path):
    done = run(f"source {SCRIPT}; echo \"url=[${{GREYFIT_TEST_DATABASE_URL:-}}]\"",
               GREYFIT_CI_PG_CONF_DIR=str(tmp_path / "nowhere"))
    assert done.returncode == 0, done
    assert "no PostgreSQL on this machine: the PostgreSQL job-store tests will be skipped" in done.stderr
    assert "url=[]" in done.stdout          # so the tests skip, with their reason shown by -rs


def test_a_database_url_already_set_is_used_as_it_is(tmp_path):
    (tmp_path / "99").mkdir()
    done = run(f"source {SCRIPT}; echo \"url=[$GREYFIT_TEST_DATABASE_URL] require=[${{GREYFIT_REQUIRE_POSTGRES:-}}]\"",
               GREYFIT_TEST_DATABASE_URL="postgresql+psycopg://elsewhere/db", GREYFIT_CI_PG_CONF_DIR=str(tmp_path),
               GREYFIT_CI_PG_PORT=str(closed_port()))
    assert done.returncode == 0, done
    assert "url=[postgresql+psycopg://elsewhere/db] require=[]" in done.stdout
    assert done.stderr == ""


def test_a_reachable_server_is_handed_to_the_tests():
    """Only where this machine's server already answers (the step would otherwise start it)."""
    with socket.socket() as s:
        s.settimeout(1)
        if s.connect_ex(("127.0.0.1", 5432)) != 0 or not any(Path("/etc/postgresql").glob("*")):
            pytest.skip("no PostgreSQL server answering on 127.0.0.1:5432 on this machine")
    done = run(f"source {SCRIPT}; echo \"url=[$GREYFIT_TEST_DATABASE_URL] require=[$GREYFIT_REQUIRE_POSTGRES]\"")
    assert done.returncode == 0, done
    assert "url=[postgresql+psycopg://postgres@127.0.0.1:5432/test] require=[1]" in done.stdout
    assert "job-store tests also run on PostgreSQL" in done.stderr
