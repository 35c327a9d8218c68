#!/usr/bin/env bash
# The main job: set up, start a simulator server on loopback, drive rule-based and random
# episodes through it over Zenoh, print the papers' metrics, stop the server.
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh
mkdir -p runs/demo
port="${OVERTAKE_DEMO_PORT:-$(.venv/bin/python -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')}"
endpoint="tcp/127.0.0.1:${port}"
.venv/bin/overtake-server --listen "$endpoint" --name demo --log-level warning \
  2> runs/demo/server.log &
server_pid=$!
trap 'kill "$server_pid" 2>/dev/null; wait "$server_pid" 2>/dev/null || true' EXIT
# The drivers wait for the server to come up (RemoteConfig.connect_timeout_s).
.venv/bin/overtake-drive --connect "$endpoint" --policy rule --episodes 4 --seed 0 \
  --json-out runs/demo/rule.json "$@"
.venv/bin/overtake-drive --connect "$endpoint" --policy random --episodes 4 --seed 0 \
  --json-out runs/demo/random.json "$@"
.venv/bin/overtake-status --connect "$endpoint"
echo "tables written to runs/demo/rule.json and runs/demo/random.json (server log: runs/demo/server.log)"
