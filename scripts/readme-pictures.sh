#!/usr/bin/env bash
# The pictures of the README and the documentation site, drawn by Rerun's own viewer
# (headless) from the demo's recording:
# runs scripts/demo.sh first when runs/demo/demo.rrd is missing (or with --fresh).
# Writes docs/pictures/demo-*.png, and replay-collision.png: a random driver's collision in heavy
# traffic, kept by overtake-drive and replayed by overtake-replay.
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
# A collision replayed: seed 1's episode, where the random driver hits a car at decision 149.
.venv/bin/overtake-drive --policy random --traffic heavy --episodes 6 --seed 0 \
  --max-decisions 300 --episodes-out runs/pictures >/dev/null
.venv/bin/overtake-replay runs/pictures/random.jsonl --episode 1 --rrd runs/pictures/replay.rrd
.venv/bin/overtake-render --recordings runs/pictures/replay.rrd \
  --out docs/pictures/replay-collision.png --width 1600 --height 1300 --timeline-time 149
