#!/usr/bin/env bash
# Lint, format check and type check, as CI runs them (scripts/setup.sh dev installs the tools).
# Usage: scripts/lint.sh            (from anywhere; exits non-zero on any finding)
set -euo pipefail
cd "$(dirname "$0")/.."
.venv/bin/ruff check .
.venv/bin/ruff format --check .
# mypy follows imports by module name, and the folders are overtake.* only once installed: a
# tree of links under build/ gives it the installed layout without installing anything.
links=build/typecheck/overtake
mkdir -p "$links"
for folder in protocol envs ipc cli viz server client trainers; do
  ln -sfn "../../../$folder" "$links/$folder"
done
(cd build/typecheck && ../../.venv/bin/mypy --config-file ../../pyproject.toml \
  --python-executable ../../.venv/bin/python -p overtake)
