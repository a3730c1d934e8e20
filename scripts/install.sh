#!/usr/bin/env bash
# Create .venv (if missing) and install greyfit into it; optional argument: extras, e.g. "test".
# The same step serves the README's commands, CI and the container image.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
[ -x .venv/bin/python ] || "$PY" -m venv .venv
.venv/bin/python -m pip install --quiet --disable-pip-version-check --upgrade pip
target=".${1:+[$1]}"
install() { .venv/bin/python -m pip install --quiet --disable-pip-version-check "$@" -e "$target"; }
# constraints.txt: the dependency versions the tests last passed with (on Python 3.11), so a fresh
# machine installs what CI tested rather than whatever was released since. Where they cannot be
# installed (another Python without their wheels) or GREYFIT_UNPINNED=1, the newest that fit
# pyproject.toml's ranges.
if [ "${GREYFIT_UNPINNED:-0}" = 1 ]; then
    install
elif ! install -c constraints.txt; then
    echo "scripts/install.sh: the versions in constraints.txt do not install with $(.venv/bin/python -V);" \
         "installing the newest versions pyproject.toml allows instead" >&2
    install
fi
# Bytecode for the project's own modules, as pip writes it for an installed wheel: with the source
# installed in place and PYTHONDONTWRITEBYTECODE set (as on CI machines), every new process (a CLI
# run, a service worker) compiled its ~100 modules again, 0.1 s of its first fit.
.venv/bin/python -m compileall -q greyfit schemas solvers service > /dev/null || true
