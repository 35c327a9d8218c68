#!/usr/bin/env bash
# Install ML-Agents' Python API (mlagents-envs 1.1.0) into .venv beside overtake, for ML-Agents'
# own wrappers over RemoteEnvironment (overtake.client.mlagents.wrappers) and tests/client/test_mlagents.py.
# mlagents-envs declares Python <= 3.10 and numpy < 1.24, yet runs on Python 3.11 and today's
# numpy: it is installed without its dependencies, and what it imports comes from overtake's
# `mlagents` extra (grpcio, gym 0.26.2, pettingzoo, ...; the protobuf there is the newer one ONNX
# needs, which the wrappers never touch).
# Usage: scripts/setup-mlagents.sh   (after scripts/setup.sh, which it runs if .venv is missing)
set -euo pipefail
cd "$(dirname "$0")/.."
[[ -x .venv/bin/python ]] || scripts/setup.sh
.venv/bin/python -m pip install --quiet -e ".[mlagents]"
.venv/bin/python -m pip install --quiet --no-deps --ignore-requires-python "mlagents-envs==1.1.0"
# ML-Agents' own side for overtake-unity-bridge (tests/client/test_unity_bridge.py): mlagents-envs'
# UnityEnvironment imports its generated protobuf modules, which need protobuf 3.20 (newer ones
# refuse them, and ONNX in .venv needs a newer one), so it gets an environment of its own, as an
# ML-Agents user's would be: .venv-mlagents, with nothing of overtake in it. The bridge itself
# runs in .venv and reads the same message definitions with today's protobuf.
# Python 3.10 where there is one (ML-Agents' own, and protobuf 3.20.3 has its C++ parser only up
# to 3.10: on 3.11 ML-Agents parses every message in pure Python, 1.9x slower through the bridge
# at 8 arenas, bench/RESULTS.md); OVERTAKE_MLAGENTS_PYTHON chooses another.
ml_python=""
for candidate in "${OVERTAKE_MLAGENTS_PYTHON:-}" python3.10 \
  "${PYENV_ROOT:-$HOME/.pyenv}"/versions/3.10*/bin/python python3; do
  if [[ -n "$candidate" ]] && "$candidate" -c "import venv" 2> /dev/null; then
    ml_python="$candidate"
    break
  fi
done
if [[ -z "$ml_python" ]]; then
  echo "no Python found for .venv-mlagents (tried \$OVERTAKE_MLAGENTS_PYTHON, python3.10, pyenv's 3.10, python3)" >&2
  exit 1
fi
if [[ ! -x .venv-mlagents/bin/python ]]; then
  "$ml_python" -m venv .venv-mlagents
fi
.venv-mlagents/bin/python -m pip install --quiet --upgrade pip
.venv-mlagents/bin/python -m pip install --quiet "protobuf==3.20.3" "grpcio>=1.48" numpy \
  "pillow>=9" "cloudpickle>=2" "filelock>=3" pyyaml "gym==0.26.2"
.venv-mlagents/bin/python -m pip install --quiet --no-deps --ignore-requires-python \
  "mlagents-envs==1.1.0"
