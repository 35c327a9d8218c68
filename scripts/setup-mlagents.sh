#!/usr/bin/env bash
# Install ML-Agents' Python API (mlagents-envs 1.1.0) into .venv beside overtake, for ML-Agents'
# own wrappers over RemoteEnvironment (overtake.client.mlagents) and tests/test_mlagents.py.
# mlagents-envs declares Python <= 3.10 and numpy < 1.24, yet runs on Python 3.11 and today's
# numpy: it is installed without its dependencies, and what it imports comes from overtake's
# `mlagents` extra (protobuf 3.20.3, grpcio, gym 0.26.2, pettingzoo, ...).
# Usage: scripts/setup-mlagents.sh   (after scripts/setup.sh, which it runs if .venv is missing)
set -euo pipefail
cd "$(dirname "$0")/.."
[[ -x .venv/bin/python ]] || scripts/setup.sh
.venv/bin/python -m pip install --quiet -e ".[mlagents]"
.venv/bin/python -m pip install --quiet --no-deps --ignore-requires-python "mlagents-envs==1.1.0"
