#!/usr/bin/env bash
# The main job: set up, start a simulator server on loopback, drive rule-based and random
# episodes through it over Zenoh, train DQN, Double DQN and Dueling DQN briefly as three
# separate trainer processes on the same server, evaluate them, and stop the server.
set -euo pipefail
cd "$(dirname "$0")/.."
echo "setting up .venv with PyTorch (about a minute the first time, seconds after)" >&2
scripts/setup.sh train
mkdir -p runs/demo
port="${OVERTAKE_DEMO_PORT:-$(.venv/bin/python -c 'import socket; s = socket.socket(); s.bind(("127.0.0.1", 0)); print(s.getsockname()[1])')}"
endpoint="tcp/127.0.0.1:${port}"
.venv/bin/overtake-server --listen "$endpoint" --name demo --log-level warning \
  2> runs/demo/server.log &
server_pid=$!
trainer_pids=()
spectator_pid=""
cleanup() {
  for pid in "${trainer_pids[@]}" $spectator_pid; do kill "$pid" 2>/dev/null || true; done
  kill "$server_pid" 2>/dev/null || true
  wait 2>/dev/null || true
}
trap cleanup EXIT
echo "a simulator server on $endpoint; driving the rule-based and random drivers through it" >&2
# The drivers and trainers wait for the server to come up (RemoteConfig.connect_timeout_s).
.venv/bin/overtake-drive --connect "$endpoint" --policy rule --episodes 4 --seed 0 \
  --json-out runs/demo/rule.json "$@"
.venv/bin/overtake-drive --connect "$endpoint" --policy random --episodes 4 --seed 0 \
  --json-out runs/demo/random.json "$@"
# A short taste of training (Min et al.'s notebook trains a million steps, their paper states
# no budget; see bench/RESULTS.md).
# One Rerun recording id for the three trainers: their .rrd files open as one recording.
recording_id="overtake-demo-$(date +%Y%m%d-%H%M%S)"
for algo in dqn ddqn dueling; do
  rm -rf "runs/demo/$algo"
  .venv/bin/overtake-train --connect "$endpoint" --algo "$algo" --inputs both --num-envs 2 \
    --total-steps "${OVERTAKE_DEMO_STEPS:-2000}" --learning-starts 500 \
    --epsilon-decay-steps 1500 --target-update-steps 500 --replay-size 5000 \
    --torch-threads 1 --no-progress --run-dir "runs/demo/$algo" --recording-id "$recording_id" \
    > "runs/demo/$algo.log" 2>&1 &
  trainer_pids+=("$!")
done
echo "training dqn, ddqn and dueling on the server, about a minute (logs: runs/demo/{dqn,ddqn,dueling}.log)"
# A spectator records the arenas while they train (read-only: it never slows the simulation).
.venv/bin/overtake-spectate --connect "$endpoint" --server demo --no-rays --seconds 600 \
  --rrd runs/demo/world.rrd --overwrite --recording-id "$recording_id" 2> runs/demo/spectate.log &
spectator_pid=$!
for pid in "${trainer_pids[@]}"; do wait "$pid"; done
trainer_pids=()
kill -TERM "$spectator_pid" && wait "$spectator_pid" || true
spectator_pid=""
# One file, one layout: the roads each trainer drove beside the three trainers' curves.
.venv/bin/overtake-layout --recordings runs/demo/world.rrd runs/demo/{dqn,ddqn,dueling}/trainer.rrd \
  --out runs/demo/demo.rrd
.venv/bin/overtake-status --connect "$endpoint"
for algo in dqn ddqn dueling; do
  .venv/bin/overtake-eval --connect "$endpoint" --checkpoint "runs/demo/$algo/checkpoint.pt" \
    --episodes 2 --max-decisions 200 --seed 1000 --json-out "runs/demo/eval-$algo.json"
done
.venv/bin/overtake-eval --connect "$endpoint" --policy rule --episodes 2 --max-decisions 200 \
  --seed 1000 --json-out runs/demo/eval-rule.json
echo
echo "The three trainers beside the rule-based driver (2 episodes of 200 decisions, seeds 1000-1001):"
.venv/bin/overtake-eval --table runs/demo/eval-{dqn,ddqn,dueling,rule}.json
echo "tables written to runs/demo/*.json; training runs in runs/demo/{dqn,ddqn,dueling} (server log: runs/demo/server.log)"
echo "open the Rerun recording (the roads and the three trainers, laid out): .venv/bin/rerun runs/demo/demo.rrd"
