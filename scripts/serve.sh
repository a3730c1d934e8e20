#!/usr/bin/env bash
# Set up .venv with greyfit (and matplotlib, for the report pages), then run the service on the
# embedded defaults (SQLite under ./data, local worker processes). Extra arguments go to `greyfit serve` (e.g. --port 8080 --workers 4).
set -euo pipefail
cd "$(dirname "$0")/.."
bash scripts/install.sh report
exec .venv/bin/greyfit serve "$@"
