#!/usr/bin/env bash
# Create .venv (if missing) and install greyfit into it; optional argument: extras, e.g. "test".
# The same step serves the README's commands, CI and the container image.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/python -m pip install --quiet --disable-pip-version-check --upgrade pip
.venv/bin/python -m pip install --quiet --disable-pip-version-check -e ".${1:+[$1]}"
