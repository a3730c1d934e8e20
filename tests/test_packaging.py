"""The container and the README use the one install step that CI exercises on every run."""
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_dockerfile_installs_with_the_project_script_and_serves_as_non_root():
    text = (ROOT / "Dockerfile").read_text()
    assert "bash scripts/install.sh" in text
    assert re.search(r"^USER greyfit$", text, re.M)
    assert "HEALTHCHECK" in text and "/healthz" in text
    assert 'VOLUME ["/data"]' in text
    assert '"greyfit", "serve"' in text or 'greyfit", "serve' in text
    # an init as PID 1 reaps what a killed worker leaves, and ends the container with the server
    assert re.search(r"apt-get install .*\btini\b", text) and 'ENTRYPOINT ["/usr/bin/tini", "--"]' in text
    # dependencies are installed before the source is copied, at the versions CI tested
    assert text.index("bash scripts/install.sh") < text.index("COPY --chown=greyfit solvers")
    assert re.search(r"^COPY .*constraints\.txt", text, re.M).start() < text.index("bash scripts/install.sh")
    # and the source's bytecode is in the image (a container's first fit would compile it)
    assert text.rindex("compileall") > text.index("COPY --chown=greyfit solvers")
    assert "compileall" in (ROOT / "scripts" / "install.sh").read_text()


def test_install_uses_the_tested_versions():
    """install.sh installs constraints.txt's versions; they name every dependency of every extra."""
    assert "-c constraints.txt" in (ROOT / "scripts" / "install.sh").read_text()
    pinned = {re.split(r"[=<>!~]", line)[0].strip().lower().replace("_", "-")
              for line in (ROOT / "constraints.txt").read_text().splitlines() if line and not line.startswith("#")}
    declared = re.findall(r'"([A-Za-z0-9_.-]+)(?:\[[^\]]*\])?\s*[<>=~!]', (ROOT / "pyproject.toml").read_text())
    assert {"casadi", "matplotlib", "schemathesis"} <= set(declared)
    missing = {d.lower().replace("_", "-") for d in declared} - pinned - {"setuptools"}
    assert not missing, f"constraints.txt lacks {sorted(missing)}: bash scripts/update_constraints.sh"


def test_readme_commands_are_the_scripts_ci_runs():
    readme = (ROOT / "README.md").read_text()
    assert "bash scripts/serve.sh" in readme and "bash scripts/test.sh" in readme
    assert "bash scripts/test.sh" in (ROOT / ".ci" / "run").read_text()
    for script in ("serve.sh", "test.sh"):
        assert "bash scripts/install.sh" in (ROOT / "scripts" / script).read_text()
