#!/usr/bin/env bash
# Set up .venv with greyfit and its test, report and docs extras, build the docs site in strict mode,
# then run the whole test suite.
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh test,report,docs,quick
# The report test opens the HTML page in a real headless browser: Chromium from the distribution,
# installed when missing and we can (root with apt-get); otherwise that test skips and says why.
if ! command -v chromium >/dev/null 2>&1 && command -v apt-get >/dev/null 2>&1 && [ "$(id -u)" = 0 ]; then
    (apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null) \
        || echo "scripts/test.sh: could not install chromium; the browser test will skip" >&2
fi
# The gate: ruff, mypy on greyfit.schemas and greyfit.solvers, import-linter's layer contracts
# (scripts/lint.sh; configuration in pyproject.toml). A finding fails the run before the tests.
bash scripts/lint.sh .venv/bin/python
# The docs site (mkdocs.yml) in strict mode: a broken link, a page left out of the navigation or an
# option table that no longer builds from the schemas fails the run. No network needed.
NO_MKDOCS_2_WARNING=1 .venv/bin/mkdocs build --strict --quiet
# the slowest tests are listed at the end, so a run that grows shows where; the tests run in one
# worker process per core (pytest-xdist, at most 4): every test keeps its own temporary folders,
# ports and PostgreSQL schema, and the compile cache is shared safely between processes
exec .venv/bin/python -m pytest -q --durations=25 -n auto --maxprocesses 4 "$@"
