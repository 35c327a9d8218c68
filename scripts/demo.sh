#!/usr/bin/env bash
# The main job: set up, then drive rule-based and random episodes and print the papers' metrics.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
mkdir -p runs/demo
.venv/bin/overtake-drive --policy rule --episodes 4 --seed 0 --json-out runs/demo/rule.json "$@"
.venv/bin/overtake-drive --policy random --episodes 4 --seed 0 --json-out runs/demo/random.json "$@"
echo "tables written to runs/demo/rule.json and runs/demo/random.json"
