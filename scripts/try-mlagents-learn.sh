#!/usr/bin/env bash
# mlagents-learn (ML-Agents 1.1.0's PPO) training on overtake through overtake-unity-bridge.
# Usage: scripts/try-mlagents-learn.sh [CONFIG]   (default examples/mlagents/ppo-min2018.yaml)
#
# mlagents 1.1.0 declares Python <= 3.10.12, numpy < 1.24, protobuf < 3.21 and onnx 1.15, none of
# which .venv can hold (ONNX export there needs protobuf >= 6), so it gets .venv-mlagents-learn:
# installed without dependency resolution (--no-deps --ignore-requires-python) and given what it
# imports at versions that run on Python 3.11 (the local CPU PyTorch 2.13.0, numpy 1.23.5,
# protobuf 3.20.3, tensorboard 2.15.2, setuptools < 81 for pkg_resources). mlagents-learn
# without --env listens on port 5004, as for the Unity editor; the bridge dials it there.
set -euo pipefail
cd "$(dirname "$0")/.."
config="${1:-examples/mlagents/ppo-min2018.yaml}"
[[ -x .venv/bin/python ]] || scripts/setup.sh
python_bin="${PYTHON:-python3}"
venv=.venv-mlagents-learn
if [[ ! -x $venv/bin/mlagents-learn ]]; then
  "$python_bin" -m venv "$venv"
  $venv/bin/python -m pip install --quiet --upgrade pip
  $venv/bin/python -m pip install --quiet "torch==2.13.0"
  $venv/bin/python -m pip install --quiet --no-deps --ignore-requires-python \
    "mlagents==1.1.0" "mlagents-envs==1.1.0"
  $venv/bin/python -m pip install --quiet "numpy==1.23.5" "protobuf==3.20.3" "grpcio>=1.48" \
    "tensorboard==2.15.2" "onnx==1.15.0" "cattrs>=1.1.0,<1.7" "attrs>=19.3.0" "h5py>=2.9.0" \
    pyyaml "pillow>=9" six "huggingface-hub>=0.14" "cloudpickle>=2" "filelock>=3" \
    "setuptools<81"
fi
if (echo > /dev/tcp/127.0.0.1/5004) 2>/dev/null; then
  echo "port 5004 is taken: mlagents-learn without --env listens there" >&2
  exit 1
fi
out=runs/mlagents-learn
mkdir -p "$out"
port=$(.venv/bin/python -c "import socket; s = socket.socket(); s.bind(('127.0.0.1', 0)); print(s.getsockname()[1])")
.venv/bin/overtake-server --listen "tcp/127.0.0.1:$port" --name mlagents-learn \
  --log-level warning > "$out/server.log" 2>&1 &
server=$!
# mlagents-learn through scripts/mlagents_learn.py: its closing ONNX export with PyTorch's
# TorchScript-based exporter (the default one needs onnxscript, which needs numpy >= 2).
$venv/bin/python scripts/mlagents_learn.py "$config" --run-id ppo-min2018 --force \
  --results-dir "$out" --torch-device cpu > "$out/mlagents-learn.log" 2>&1 &
learner=$!
cleanup() { kill "$server" "$learner" 2> /dev/null || true; }
trap cleanup EXIT
for _ in $(seq 120); do
  (echo > /dev/tcp/127.0.0.1/5004) 2> /dev/null && break
  kill -0 "$learner" 2> /dev/null || { tail -20 "$out/mlagents-learn.log"; exit 1; }
  sleep 0.5
done
.venv/bin/overtake-unity-bridge --connect "tcp/127.0.0.1:$port" --port 5004 --arenas 4 \
  2>&1 | tee "$out/bridge.log"
learn_status=0
wait "$learner" || learn_status=$?
grep -E "Step: [0-9]+" "$out/mlagents-learn.log" || true
ls "$out"/ppo-min2018/*/*.pt
if ((learn_status != 0)); then
  echo "mlagents-learn exited with $learn_status after training; its last lines:" >&2
  tail -3 "$out/mlagents-learn.log" >&2
  exit "$learn_status"
fi
# The model mlagents-learn exported, loaded and run once in ONNX Runtime.
.venv/bin/python - "$out"/ppo-min2018/*.onnx <<'PY'
import sys

import numpy as np
import onnxruntime as ort

session = ort.InferenceSession(sys.argv[1], providers=["CPUExecutionProvider"])
feeds = {}
for tensor in session.get_inputs():
    shape = [1 if not isinstance(d, int) or d < 1 else d for d in tensor.shape]
    kind = np.float32 if "float" in tensor.type else np.int64
    feeds[tensor.name] = np.zeros(shape, dtype=kind)
outputs = session.run(None, feeds)
print(f"{sys.argv[1]}: {len(session.get_inputs())} inputs, {len(outputs)} outputs, "
      "runs in ONNX Runtime")
PY
