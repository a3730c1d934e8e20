"""The docs say what the code does: option tables complete, the tutorial's numbers real, no stale names.

The site itself is built in strict mode by scripts/test.sh (`mkdocs build --strict`) before the
tests; these check what a strict build cannot: that the generated tables hold every option with a
meaning, that the tutorial's printed estimates are what its commands give, and that user-facing
text cites the source documents by title.
"""
import importlib.util
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

import greyfit
from greyfit.schemas.discovery import DiscoveryOptions
from greyfit.schemas.fit import FitOptions
from greyfit.schemas.frequency import FrequencyFitOptions
from greyfit.schemas.online import MrasOptions, Prefilter, RlsOptions

ROOT = Path(__file__).resolve().parents[1]
OPTION_MODELS = (FitOptions, RlsOptions, MrasOptions, Prefilter, DiscoveryOptions, FrequencyFitOptions)
SEED_WORDING = re.compile(r"\bseeds? 0\d\d\b", re.I)   # "seed 001": the documents' file numbers
# an engineering log's references, which a reader of the docs cannot follow: commit hashes, branches
# ("this branch against main", "main's registry") and issue numbers
LOG_WORDING = re.compile(r"\bcommit [0-9a-f]{7,40}\b|\bbranch\b|\bissue #\d|\b(?:on|against) main\b|\bmain's\b",
                         re.I)


def docs_hook():
    spec = importlib.util.spec_from_file_location("greyfit_docs", ROOT / "docs" / "hooks" / "greyfit_docs.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("model", OPTION_MODELS, ids=lambda m: m.__name__)
def test_every_option_has_a_description(model):
    missing = [name for name, field in model.model_fields.items() if not (field.description or "").strip()]
    assert not missing, f"{model.__name__}: give {missing} a description= (the options page and OpenAPI show it)"


def test_the_generated_options_table_lists_every_fit_option_with_its_default():
    table = docs_hook().fields_tables(FitOptions)
    rows = {m.group(1): m.group(0) for m in re.finditer(r"^\| `(\w+)` \|.*$", table, re.M)}
    for model in (FitOptions, RlsOptions, MrasOptions, Prefilter):
        for name in model.model_fields:
            assert name in rows, f"{model.__name__}.{name} is not in the options table"
    assert "| `max_iter` | integer | `200` | Ipopt iterations per start at most (≥ 1, ≤ 10000) |" in table
    assert "`\"gauss_newton\"`" in rows["hessian"] and "`0.95`" in rows["confidence_level"]
    assert "`0.99`" in rows["forgetting"]    # a nested model's default, from RlsOptions itself


def test_the_settings_table_names_every_variable_and_keeps_placeholders_as_text():
    from greyfit.service.settings import Settings

    table = docs_hook().settings_table(Settings)
    for name in Settings.model_fields:
        assert f"| `GREYFIT_{name.upper()}` |" in table, name
    assert "— |" not in table, "a setting without a description: give it description= in service/settings.py"
    assert "sqlite:///&lt;data_dir&gt;/greyfit.db" in table   # not swallowed as an HTML tag


def test_user_facing_text_cites_the_source_documents_by_title():
    pages = [ROOT / "README.md", ROOT / "CHANGELOG.md", *sorted((ROOT / "docs").glob("*.md"))]
    for page in pages:
        hits = SEED_WORDING.findall(page.read_text(encoding="utf-8"))
        assert not hits, f"{page.relative_to(ROOT)} says {hits}: cite the document by its title (docs/sources.md)"
    from greyfit.service.http.app import create_app
    from greyfit.service.settings import Settings

    spec = json.dumps(create_app(Settings(data_dir=ROOT / "build" / "docs-test")).openapi(), ensure_ascii=False)
    assert not SEED_WORDING.findall(spec)


def test_user_facing_text_names_no_commit_branch_or_issue():
    pages = [ROOT / "README.md", ROOT / "CHANGELOG.md", *sorted((ROOT / "docs").rglob("*.md"))]
    for page in pages:
        hits = LOG_WORDING.findall(page.read_text(encoding="utf-8"))
        assert not hits, (f"{page.relative_to(ROOT)} says {hits}: say what was measured and on what machine, "
                          "as a user's page would, without commit hashes, branches or issue numbers")


def test_readme_is_short_and_links_pages_that_exist():
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(readme.encode()) <= 10 * 1024
    for link in re.findall(r"\]\(((?:docs/)?[\w./-]+\.md|LICENSE|CHANGELOG\.md)\)", readme):
        assert (ROOT / link).exists(), link
    assert "MIT" in (ROOT / "LICENSE").read_text() and 'license = "MIT"' in (ROOT / "pyproject.toml").read_text()


@pytest.fixture(scope="module")
def tutorial_result(tmp_path_factory):
    made = subprocess.run([sys.executable, str(ROOT / "docs" / "tutorial" / "make_rc_request.py")],
                          capture_output=True, text=True, check=True)
    request = greyfit.FitRequest.model_validate_json(made.stdout)
    return request, greyfit.fit(request)


def test_the_tutorial_fit_finds_the_circuit_it_was_simulated_with(tutorial_result):
    request, result = tutorial_result
    truth = {"R": 1000.0, "C": 1e-3}
    start = {p.name: p.value for p in request.model.parameters}
    assert all(abs(start[n] / truth[n] - 1) >= 0.5 for n in truth)     # a rough start, as the page says
    assert result.status == "success" and result.quality == "good", result.warnings
    for name, value in truth.items():
        p = result.parameters[name]
        assert abs(p.value - value) < 0.001 * value and abs(p.value - value) < 4 * p.stderr, (name, p)
        assert p.ci95[0] < value < p.ci95[1]
    assert result.validation.fit_percent["v"] > 99 and result.validation.fit_percent["i"] > 99


def test_the_tutorial_page_prints_what_the_fit_gives(tutorial_result):
    """The page's numbers are the fit's, to within one unit of the last digit shown."""
    _, result = tutorial_result
    page = (ROOT / "docs" / "tutorial.md").read_text(encoding="utf-8")

    def printed(pattern: str) -> tuple[float, float]:
        match = re.search(pattern, page)
        assert match, f"docs/tutorial.md no longer shows {pattern}"
        text = match.group(1)
        return float(text), 10.0 ** -len(text.partition(".")[2])

    R, C = result.parameters["R"], result.parameters["C"]
    shown = {"R": (r'"R": \{"value": ([\d.]+)', R.value),
             "C": (r'"C": \{"value": ([\d.]+)', C.value),
             "stderr of R": (r'"R": \{[^}]*"stderr": ([\d.]+)', R.stderr),
             "fit % of v": (r'"fit_percent": \{"v": ([\d.]+)', result.metrics.fit_percent["v"]),
             "validation fit % of v": (r'"validation": \{.*?"fit_percent": \{"v": ([\d.]+)',
                                       result.validation.fit_percent["v"]),
             "iterations": (r'"iterations": (\d+)', result.solver.iterations)}
    for what, (pattern, actual) in shown.items():
        on_page, unit = printed(pattern)
        assert abs(on_page - actual) <= unit, \
            f"docs/tutorial.md shows {what} = {on_page}, the fit gives {actual}: update the page"
