#!/usr/bin/env bash
# The gate before the tests: ruff (the configured rules and import order), mypy on the contract and
# the numerics and the service, and import-linter's layer contracts (pyproject.toml holds all three configurations).
# Exits non-zero on the first failing check. Usage: bash scripts/lint.sh [python]  (default .venv's)
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${1:-.venv/bin/python}
BIN=$(cd "$(dirname "$PY")" && pwd)   # absolute: mypy and import-linter run from the stage

echo "lint: ruff"
"$BIN/ruff" check --quiet .

# mypy and import-linter follow the installed names (greyfit.schemas, ...); the folders are mapped
# by setuptools' package-dir, which neither tool reads, so they look at a staged copy of that layout.
stage=build/lint
rm -rf "$stage" && mkdir -p "$stage/greyfit"
cp greyfit/*.py greyfit/py.typed "$stage/greyfit/"
for d in schemas solvers service; do
    cp -r "$d" "$stage/greyfit/$d"
done
find "$stage" -name __pycache__ -prune -exec rm -rf {} +

echo "lint: mypy greyfit.schemas greyfit.solvers greyfit.service"
(cd "$stage" && "$BIN/mypy" --config-file "$OLDPWD/pyproject.toml" --cache-dir "$OLDPWD/build/mypy_cache" \
    -p greyfit.schemas -p greyfit.solvers -p greyfit.service)

echo "lint: import-linter"
(cd "$stage" && PYTHONPATH=. "$BIN/lint-imports" "$OLDPWD/pyproject.toml" --no-cache)
