"""What ML-Agents' own wire costs: overtake through ``overtake-unity-bridge`` against overtake's
own ML-Agents-style client on the same server.

One ``overtake.server`` subprocess on 127.0.0.1 (a free port); for each arena count, in
alternating rounds (ABAB...), the same loop of ML-Agents' low-level API (``get_steps``, random
allowed actions through ``set_actions``, ``step``) driven two ways:

* direct: :class:`overtake.client.RemoteEnvironment` in this process (Zenoh to the server);
* bridge: mlagents-envs 1.1.0's own ``UnityEnvironment`` in .venv-mlagents
  (``bench/speed/mlagents_driver.py``), served by an ``overtake-unity-bridge`` subprocess that
  steps the same kind of arenas on the same server (gRPC between the two, then Zenoh).

Each round times ``--steps`` decisions after ``--warmup`` untimed ones (the bridge's processes
start fresh each round, outside the timing). The figure is the ratio of the bridge's steps per
second to the direct client's, round by round, and the bridge's cost per step in ms
(1/bridge - 1/direct). Preset min2018 with both sensors, 1 agent per arena.

    .venv/bin/python -m bench.speed.bench_unity_bridge [--arenas 1 8] [--rounds 3] [--json PATH]
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import tyro

from bench.harness import free_port, start_server, stop_process, write_report
from bench.speed.bench_sim import machine_description

ROOT = Path(__file__).resolve().parents[2]
ML_PYTHON = Path(os.environ.get("OVERTAKE_ML_PYTHON", ROOT / ".venv-mlagents" / "bin" / "python"))
DRIVER = Path(__file__).resolve().parent / "mlagents_driver.py"


@dataclass(frozen=True)
class BridgeBenchConfig:
    arenas: tuple[int, ...] = (1, 8)
    steps: int = 300
    """timed decisions per round"""
    warmup: int = 30
    rounds: int = 3
    json: Path | None = None


def direct_round(endpoint: str, arenas: int, config: BridgeBenchConfig) -> float:
    """Steps per second of RemoteEnvironment driven as ML-Agents' API is."""
    from overtake.client.mlagents.environment import RemoteEnvironment

    env = RemoteEnvironment(endpoint, preset="min2018", arenas=arenas, seed=0)
    rng = np.random.default_rng(0)
    name = env.behavior_name

    def drive(steps: int) -> None:
        for _ in range(steps):
            decision, _ = env.get_steps(name)
            if len(decision):
                mask = decision.action_mask[0]
                env.set_actions(name, np.array([rng.choice(np.flatnonzero(~r)) for r in mask]))
            env.step()

    try:
        drive(config.warmup)
        started = time.perf_counter()
        drive(config.steps)
        return config.steps / (time.perf_counter() - started)
    finally:
        env.close()


def bridge_round(endpoint: str, arenas: int, config: BridgeBenchConfig) -> float:
    """Steps per second of ML-Agents' UnityEnvironment through a fresh bridge."""
    port = free_port()
    ml = subprocess.Popen(
        [str(ML_PYTHON), str(DRIVER), str(port), str(config.warmup), str(config.steps)],
        stdout=subprocess.PIPE,
        text=True,
    )
    bridge = None
    try:
        import socket

        deadline = time.monotonic() + 60
        while True:  # polling: ML-Agents' gRPC server comes up in its own time
            with socket.socket() as probe:
                if probe.connect_ex(("127.0.0.1", port)) == 0:
                    break
            if ml.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError("ML-Agents' side did not listen")
            time.sleep(0.05)
        bridge = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "overtake.client.mlagents.unity_bridge",
                "--connect",
                endpoint,
                "--port",
                str(port),
                "--host",
                "127.0.0.1",
                "--arenas",
                str(arenas),
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        out, _ = ml.communicate(timeout=600)
        return float(json.loads(out.strip().splitlines()[-1])["steps_per_s"])
    finally:
        for proc in (bridge, ml):
            if proc is not None:
                stop_process(proc)


def main(config: BridgeBenchConfig) -> dict[str, Any]:
    if not ML_PYTHON.exists():
        raise SystemExit("bench_unity_bridge needs .venv-mlagents (scripts/setup-mlagents.sh)")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    server = start_server(endpoint, 60.0)
    results: dict[int, dict[str, list[float]]] = {}
    try:
        for arenas in config.arenas:
            rates: dict[str, list[float]] = {"direct": [], "bridge": []}
            for _ in range(config.rounds):
                rates["direct"].append(direct_round(endpoint, arenas, config))
                rates["bridge"].append(bridge_round(endpoint, arenas, config))
            results[arenas] = rates
    finally:
        stop_process(server)
    report: dict[str, Any] = {
        "config": {k: str(v) for k, v in vars(config).items()},
        "machine": machine_description(),
        "arenas": {},
    }
    print(f"min2018, both sensors; {config.rounds} rounds of {config.steps} decisions")
    print(f"{'arenas':>6} {'direct/s':>9} {'bridge/s':>9} {'bridge/direct':>13} {'ms/step':>8}")
    for arenas, rates in results.items():
        ratios = [b / d for b, d in zip(rates["bridge"], rates["direct"], strict=True)]
        direct, bridge = statistics.median(rates["direct"]), statistics.median(rates["bridge"])
        cost_ms = 1000 * (1 / bridge - 1 / direct)
        report["arenas"][arenas] = {
            "steps_per_s": {k: [round(v, 1) for v in vals] for k, vals in rates.items()},
            "ratios": [round(r, 3) for r in ratios],
            "median_ratio": round(statistics.median(ratios), 3),
            "bridge_cost_ms_per_step": round(cost_ms, 3),
        }
        print(
            f"{arenas:>6} {direct:9.1f} {bridge:9.1f} {statistics.median(ratios):12.2f}x "
            f"{cost_ms:8.2f}   (rounds {[round(r, 2) for r in ratios]})"
        )
    write_report(config.json, report)
    return report


if __name__ == "__main__":
    main(tyro.cli(BridgeBenchConfig))
