#!/usr/bin/env bash
# The pictures of the README and the documentation site, drawn by Rerun's own viewer
# (headless) from the demo's recording:
# runs scripts/demo.sh first when runs/demo/demo.rrd is missing (or with --fresh).
# Writes docs/pictures/demo-*.png.
set -euo pipefail
cd "$(dirname "$0")/.."
if [[ "${1:-}" == "--fresh" || ! -f runs/demo/demo.rrd ]]; then
  scripts/demo.sh
fi
scripts/setup-viewer.sh
mkdir -p docs/pictures
.venv/bin/overtake-render --recordings runs/demo/demo.rrd --out docs/pictures/demo.png \
  --width 1600 --height 1000 \
  --tabs compare "training: *" "demo arena * (dqn)" cars
