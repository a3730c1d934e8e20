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
    # dependencies are installed before the source is copied
    assert text.index("bash scripts/install.sh") < text.index("COPY --chown=greyfit solvers")


def test_readme_commands_are_the_scripts_ci_runs():
    readme = (ROOT / "README.md").read_text()
    assert "bash scripts/serve.sh" in readme and "bash scripts/test.sh" in readme
    assert "bash scripts/test.sh" in (ROOT / ".ci" / "run").read_text()
    for script in ("serve.sh", "test.sh"):
        assert "bash scripts/install.sh" in (ROOT / "scripts" / script).read_text()
