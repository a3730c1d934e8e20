#!/usr/bin/env bash
# Re-resolve every dependency (all extras) to its newest version in a scratch environment and write
# the result to constraints.txt, the versions scripts/install.sh installs. Run the tests after it.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}
tmp=$(mktemp -d)
trap 'rm -rf "$tmp"' EXIT
"$PY" -m venv "$tmp/venv"
"$tmp/venv/bin/python" -m pip install --quiet --disable-pip-version-check --upgrade pip
"$tmp/venv/bin/python" -m pip install --quiet --disable-pip-version-check -e ".[test,report,postgres,dask,docs,bench,quick]"
{
    sed -n '/^#/p' constraints.txt
    "$tmp/venv/bin/python" -m pip freeze --exclude-editable
} > "$tmp/constraints.txt"
mv "$tmp/constraints.txt" constraints.txt
echo "constraints.txt: $(grep -vc '^#' constraints.txt) packages"
