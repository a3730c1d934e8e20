#!/usr/bin/env bash
# Set up a virtual environment (.venv) with greyfit, then run the service on the embedded defaults
# (SQLite under ./data, local worker processes). Extra arguments go to `greyfit serve`.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/python -m pip install --quiet --upgrade pip
.venv/bin/python -m pip install --quiet -e .
exec .venv/bin/greyfit serve "$@"
