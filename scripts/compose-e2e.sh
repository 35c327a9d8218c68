#!/usr/bin/env bash
# The real docker-compose.yml on a Docker engine, end to end: builds both images (offline where
# this host needs it), brings the stack up, checks health, stepping, the viewer, restart and
# resume, --scale, stop and down, and writes the figures to runs/compose-e2e/summary.json.
# bench/reliability/compose_e2e.py says exactly what it checks; its options: --help.
# Needs a running Docker engine (docs/compose.md), and root where no
# registry is reachable (the base image is then made with debootstrap).
set -euo pipefail
cd "$(dirname "$0")/.."
scripts/setup.sh dev
exec .venv/bin/python -m bench.reliability.compose_e2e "$@"
