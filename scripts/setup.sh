#!/usr/bin/env bash
# Create .venv (if missing) and install overtake into it with the extras given as arguments.
# Usage: scripts/setup.sh [extra,...]     e.g. scripts/setup.sh dev
set -euo pipefail
cd "$(dirname "$0")/.."
python_bin="${PYTHON:-python3}"
if [[ ! -x .venv/bin/python ]]; then
  "$python_bin" -m venv .venv
fi
.venv/bin/python -m pip install --quiet --upgrade pip
# PyTorch first, pinned: the pin resolves to the CPU wheel, while an unpinned torch (or a
# range that admits a newer release) would pull gigabytes of CUDA packages.
.venv/bin/python -m pip install --quiet "torch==2.13.0"
extras="${1:-}"
target="."
[[ -n "$extras" ]] && target=".[${extras}]"
.venv/bin/python -m pip install --quiet -e "$target"
