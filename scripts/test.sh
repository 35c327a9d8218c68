#!/usr/bin/env bash
# Set up with the dev extra, then run the default test suite (slow tests excluded).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh dev
# Xvfb and software Vulkan where they can be installed: one test draws a recording with Rerun's
# own viewer (it skips, saying why, where they are missing).
scripts/setup-viewer.sh
exec .venv/bin/python -m pytest "$@"
