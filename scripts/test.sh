#!/usr/bin/env bash
# Set up with the dev extra (and RLlib, for its example's test), then run the default test
# suite (slow tests excluded).
set -euo pipefail
cd "$(dirname "$0")/.."
echo "setting up .venv with the dev tools (a few minutes the first time, seconds after)" >&2
scripts/setup.sh dev,rllib
# Xvfb and software Vulkan where they can be installed: one test draws a recording with Rerun's
# own viewer (it skips, saying why, where they are missing).
scripts/setup-viewer.sh
# ML-Agents' Python API: tests/client/test_mlagents.py runs ML-Agents' own wrappers on overtake (it
# skips, saying why, where the API cannot be installed).
scripts/setup-mlagents.sh || echo "mlagents-envs could not be installed: tests/client/test_mlagents.py will skip" >&2
exec .venv/bin/python -m pytest "$@"
