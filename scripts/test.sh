#!/usr/bin/env bash
# Set up with the dev extra, then run the default test suite (slow tests excluded).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh dev
exec .venv/bin/python -m pytest "$@"
