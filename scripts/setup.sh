#!/usr/bin/env bash
# Create .venv (if missing) and install overtake into it with the extras given as arguments.
# Usage: scripts/setup.sh [extra,...]     e.g. scripts/setup.sh dev
set -euo pipefail
cd "$(dirname "$0")/.."
# overtake needs Python 3.11 or newer. PYTHON names the one to build .venv with (default
# python3); a .venv another Python made is replaced, saying so, rather than kept half-working.
python_bin="${PYTHON:-python3}"
minimum="3.11"
version_of() {  # "MAJOR.MINOR" of the Python $1, or nothing if it does not run
  "$1" -c 'import sys; print("%d.%d" % sys.version_info[:2])' 2>/dev/null || true
}
new_enough() {  # whether version $1 is at least $minimum
  [[ -n "$1" ]] && [[ "$(printf '%s\n%s\n' "$minimum" "$1" | sort -V | head -1)" == "$minimum" ]]
}
venv_version=""
[[ -x .venv/bin/python ]] && venv_version="$(version_of .venv/bin/python)"
# Without PYTHON, a working .venv of a recent enough Python is kept as it is.
if [[ -n "${PYTHON:-}" || -z "$venv_version" ]] || ! new_enough "$venv_version"; then
  wanted="$(version_of "$python_bin")"
  if ! new_enough "$wanted"; then
    found="${wanted:-not found or not runnable}"
    echo "scripts/setup.sh: overtake needs Python $minimum or newer; $python_bin is $found." \
      "Name one with PYTHON, e.g. PYTHON=python3.11 $0 (scripts/demo.sh and scripts/test.sh" \
      "take PYTHON too)" >&2
    exit 1
  fi
  if [[ -e .venv && "$venv_version" != "$wanted" ]]; then
    echo "scripts/setup.sh: .venv was made by Python ${venv_version:-(broken)}, not $python_bin" \
      "($wanted): replacing it" >&2
    rm -rf .venv
  fi
fi
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
# The editable install's build warns, in a box, about folders named like the package: this
# project's folders are the package (pyproject maps them), nothing a user can act on.
PYTHONWARNINGS=ignore .venv/bin/python -m pip install --quiet -e "$target"
