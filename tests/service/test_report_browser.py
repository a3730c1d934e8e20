"""The HTML report opened in a real headless browser (Chromium from the distribution's packages)."""
import json
import re
import shutil
import struct
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pytest

from tests.solvers.test_validation import DUFFING_TRUTH, duffing_input, duffing_model, record, simulate_duffing

ROOT = Path(__file__).resolve().parents[2]
FIGURES = ("compare_estimation", "compare_validation", "residuals_time", "residuals", "parameters", "correlation")


def browser() -> str:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    pytest.skip("no headless browser: install Chromium (apt-get install -y chromium; scripts/test.sh does "
                "it when run as root with apt-get)")


def png_size(path: Path) -> tuple[int, int]:
    head = path.read_bytes()[:24]
    assert head[:8] == b"\x89PNG\r\n\x1a\n", f"{path} is not a PNG"
    return struct.unpack(">II", head[16:24])


def chromium(exe: str, *args: str) -> subprocess.CompletedProcess:
    profile = tempfile.mkdtemp(prefix="greyfit-chromium-")
    try:
        return subprocess.run([exe, "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                               "--no-first-run", f"--user-data-dir={profile}", *args],
                              capture_output=True, text=True, timeout=120)
    finally:
        shutil.rmtree(profile, ignore_errors=True)


@pytest.fixture(scope="module")
def report_dir(tmp_path_factory):
    """`greyfit report` on a Duffing fit with a contiguous validation record."""
    pytest.importorskip("matplotlib", reason="the report extra is not installed (pip install 'greyfit[report]')")
    tmp = tmp_path_factory.mktemp("report")
    t = np.linspace(0, 30, 601)
    u = duffing_input(t)
    x = simulate_duffing(t, DUFFING_TRUTH, (0.5, 0.0), u)
    request = {"model": duffing_model(), "experiments": [record("est", t[:301], x[:, :301], u[:301], 1)],
               "validation": [record("val", t[300:], x[:, 300:], u[300:], 2)], "options": {"substeps": 2}}
    (tmp / "request.json").write_text(json.dumps(request))
    fit = subprocess.run([sys.executable, "-m", "greyfit.service.cli", "fit", str(tmp / "request.json")],
                         cwd=ROOT, capture_output=True, text=True, check=True)
    (tmp / "result.json").write_text(fit.stdout)
    subprocess.run([sys.executable, "-m", "greyfit.service.cli", "report", str(tmp / "result.json"), "--request",
                    str(tmp / "request.json"), "--out", str(tmp / "out")], cwd=ROOT, check=True,
                   capture_output=True, text=True)
    return tmp / "out"


def test_report_files_are_written(report_dir):
    for name in FIGURES:
        width, height = png_size(report_dir / f"{name}.png")
        assert width >= 300 and height >= 150, (name, width, height)
        assert (report_dir / f"{name}.png").stat().st_size > 5_000
        assert (report_dir / f"{name}.svg").read_text().lstrip().startswith(("<?xml", "<svg"))
    width, height = png_size(report_dir / "compare_validation.png")
    assert 500 <= width <= 3000 and 200 <= height <= 3000


def test_report_page_loads_in_headless_chromium_with_every_figure_rendered(report_dir):
    exe = browser()
    page = report_dir / "report.html"
    dom = chromium(exe, "--dump-dom", page.as_uri())
    assert dom.returncode == 0, dom.stderr[-2000:]
    html = dom.stdout
    assert f'data-figures="{len(FIGURES)}"' in html, html[:500]
    for name in FIGURES:
        m = re.search(rf'<figure id="fig-{name}"[^>]*>\s*<img[^>]*data-rendered="(\d+)x(\d+)"', html)
        assert m, f"figure {name} missing or not decoded by the browser"
        assert int(m.group(1)) >= 300 and int(m.group(2)) >= 150, (name, m.groups())
    shot = report_dir / "page.png"
    result = chromium(exe, f"--screenshot={shot}", "--window-size=1200,2400", page.as_uri())
    assert result.returncode == 0 and shot.exists(), result.stderr[-2000:]
    assert png_size(shot) == (1200, 2400) and shot.stat().st_size > 50_000


@pytest.fixture(scope="module")
def frequency_report_dir(tmp_path_factory):
    """`greyfit fit` then `greyfit report --request` on a frequency-response fit of two PI loops
    (2 % complex noise on the measured responses)."""
    pytest.importorskip("matplotlib", reason="the report extra is not installed (pip install 'greyfit[report]')")
    from tests.frequency_systems import TRUTH, frequency_data, seed001_model
    tmp = tmp_path_factory.mktemp("freq_report")
    request = {"model": seed001_model({n: 1.5 * v for n, v in TRUTH.items()}),
               "data": [frequency_data(TRUTH, 1, 1, seed=2, name="pi_1_1"),
                        frequency_data(TRUTH, 2, 0.5, seed=3, name="pi_2_05")]}
    (tmp / "request.json").write_text(json.dumps(request))
    fit = subprocess.run([sys.executable, "-m", "greyfit.service.cli", "fit", str(tmp / "request.json")],
                         cwd=ROOT, capture_output=True, text=True, check=True)
    (tmp / "result.json").write_text(fit.stdout)
    report = subprocess.run([sys.executable, "-m", "greyfit.service.cli", "report", str(tmp / "result.json"),
                             "--request", str(tmp / "request.json"), "--out", str(tmp / "out"), "--formats", "png"],
                            cwd=ROOT, capture_output=True, text=True)
    assert report.returncode == 0, report.stderr   # exited 2 with pydantic union internals before
    return tmp / "out", json.loads(fit.stdout)


def test_frequency_report_has_bode_and_nyquist_in_headless_chromium(frequency_report_dir):
    out, result = frequency_report_dir
    assert result["success"] is True and result["frequency_response"]["stable"] is True
    for name in ("bode", "nyquist"):
        width, height = png_size(out / f"{name}.png")
        assert width >= 600 and height >= 300, (name, width, height)   # two loops side by side
    exe = browser()
    dom = chromium(exe, "--dump-dom", (out / "report.html").as_uri())
    assert dom.returncode == 0, dom.stderr[-2000:]
    html = dom.stdout
    for name in ("bode", "nyquist", "parameters"):
        m = re.search(rf'<figure id="fig-{name}"[^>]*>\s*<img[^>]*data-rendered="(\d+)x(\d+)"', html)
        assert m, f"figure {name} missing or not decoded by the browser"
        assert int(m.group(1)) >= 600 and int(m.group(2)) >= 300, (name, m.groups())
    assert 'id="fig-compare_estimation"' not in html   # no time records to compare
    # the tables: the verdict, each estimate with its value, and the loops' stability
    assert 'data-quality="good"' in html and 'data-converged="true"' in html
    for name, p in result["parameters"].items():
        assert f"<td>{name}</td><td>{p['value']:.6g}</td>" in html
    for loop in ("pi_1_1", "pi_2_05"):
        assert f"<td>{loop}</td><td>yes</td>" in html
    assert "numerator (descending powers of s): b1, 0, b2" in html
