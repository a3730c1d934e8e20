"""The built wheel installs one namespace, greyfit.*: nothing it installs collides with another
distribution's top-level package (PyPI has `schemas`, `service`, `solvers`) or a user's own folders."""
import subprocess
import sys
import sysconfig
import venv
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "-q", "-w", str(out), str(ROOT)],
                   check=True, capture_output=True, timeout=600)
    return next(out.glob("greyfit-*.whl"))


def test_the_wheel_holds_one_top_level_package_with_every_module(wheel):
    names = zipfile.ZipFile(wheel).namelist()
    tops = {n.split("/")[0] for n in names if not n.split("/")[0].endswith(".dist-info")}
    assert tops == {"greyfit"}
    assert "greyfit/py.typed" in names
    for folder in ("schemas", "solvers", "service"):
        for source in (ROOT / folder).rglob("*.py"):
            assert f"greyfit/{folder}/{source.relative_to(ROOT / folder).as_posix()}" in names, source


def test_installed_beside_a_users_schemas_and_pypis_schemas(wheel, tmp_path):
    env = tmp_path / "venv"
    venv.EnvBuilder(with_pip=True).create(env)
    py = env / "bin" / "python"
    subprocess.run([str(py), "-m", "pip", "install", "-q", "--no-deps", "--no-index", str(wheel)],
                   check=True, capture_output=True, timeout=600)
    # what `pip install schemas` does: a top-level `schemas` package of another distribution
    site = subprocess.run([str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
                          capture_output=True, text=True, check=True).stdout.strip()
    (Path(site) / "schemas").mkdir()
    (Path(site) / "schemas" / "__init__.py").write_text("raise SyntaxError('not greyfit')\n")
    # a user's project with its own schemas/ and service/ folders, run from there
    project = tmp_path / "project"
    for folder in ("schemas", "service", "solvers"):
        (project / folder).mkdir(parents=True)
        (project / folder / "__init__.py").write_text("USER = True\n")
    code = ("import schemas, greyfit; from greyfit.client import Client; from greyfit import FitRequest; "
            "from greyfit.solvers.fit import fit_model; from greyfit.service.http.app import create_app; "
            "import json; req = FitRequest.model_validate(json.load(open(%r))); r = fit_model(req); "
            "assert schemas.USER and r.success, r.message; print(greyfit.__version__, r.parameters['k'].value)"
            % str(ROOT / "examples" / "msd_request.json"))
    # the dependencies come from the test environment, greyfit only from the fresh one
    deps = sysconfig.get_paths()["purelib"]
    proc = subprocess.run([str(py), "-c", code], cwd=project, capture_output=True, text=True, timeout=600,
                          env={"PYTHONPATH": f"{project}:{deps}", "PATH": "/usr/bin:/bin",
                               "GREYFIT_CACHE_DIR": str(tmp_path / "cache")})
    assert proc.returncode == 0, proc.stderr[-3000:]
    version, k = proc.stdout.split()
    assert version == "0.1.0" and abs(float(k) - 5.0) < 0.1
