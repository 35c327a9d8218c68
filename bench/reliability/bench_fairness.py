"""How one server shares itself among trainers: steps per second of each of several equal
trainers stepping at once.

One ``overtake.server`` subprocess on 127.0.0.1 (a free port) and ``--trainers`` trainer
processes (this script in trainer mode), each stepping ``--arenas`` remote arenas of
``--preset`` (``gymnasium.make_vec("overtake/RemoteHighway-v0", ...)``) with seeded random
actions. Every trainer opens and resets its arenas, reports ready, and waits; then all start
together and step for ``--seconds``. Each reports its steps per second (vector steps: one step
of all its arenas) and its step latency p50 / p99. The share is fair when the slowest trainer's
rate is close to the fastest's: the report gives min / max.

With ``--baseline REV`` the same is measured first against a server running that git
revision's code (a temporary worktree put first on the server's PYTHONPATH; the trainers run
the working tree's code), then against the working tree's server, in the same run.

    .venv/bin/python -m bench.reliability.bench_fairness [--trainers 4] [--arenas 4] \\
        [--seconds 60] [--baseline REV] [--json PATH]
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import tyro

from bench.harness import (
    REMOTE_ENV_ID,
    baseline_checkout,
    free_port,
    make_env,
    start_server,
    stop_process,
)


@dataclass(frozen=True)
class FairnessConfig:
    trainers: int = 4
    """trainer processes stepping at once"""
    arenas: int = 4
    """remote arenas per trainer"""
    seconds: float = 60.0
    """how long every trainer steps"""
    preset: str = "min2018"
    baseline: str | None = None
    """a git revision whose server is measured too, before the working tree's"""
    json: Path | None = None


def trainer_main(endpoint: str, arenas: int, preset: str, seconds: float, seed: int) -> None:
    """Trainer mode: open, say ready, wait for the go line, step, print one JSON line."""
    from overtake.client.wire.remote import RemoteConfig

    env = make_env(REMOTE_ENV_ID, arenas, preset=preset, remote=RemoteConfig(connect=(endpoint,)))
    env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    print("ready", flush=True)
    sys.stdin.readline()
    times: list[float] = []
    started = time.perf_counter()
    while time.perf_counter() - started < seconds:
        actions = rng.integers(0, 5, size=arenas)
        t0 = time.perf_counter()
        env.step(actions)
        times.append(time.perf_counter() - t0)
    elapsed = time.perf_counter() - started
    env.close()
    ms = np.asarray(times) * 1e3
    print(
        json.dumps(
            {
                "steps_per_s": len(times) / elapsed,
                "p50_ms": float(np.percentile(ms, 50)),
                "p99_ms": float(np.percentile(ms, 99)),
            }
        ),
        flush=True,
    )


def measure(config: FairnessConfig, server_env: dict[str, str] | None) -> dict[str, Any]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    server = start_server(endpoint, 60.0, env=server_env)
    trainers: list[subprocess.Popen[str]] = []
    try:
        for index in range(config.trainers):
            trainers.append(
                subprocess.Popen(
                    [
                        sys.executable,
                        "-m",
                        "bench.reliability.bench_fairness",
                        "--trainer",
                        endpoint,
                        str(config.arenas),
                        config.preset,
                        str(config.seconds),
                        str(index),
                    ],
                    stdin=subprocess.PIPE,
                    stdout=subprocess.PIPE,
                    text=True,
                    cwd=Path(__file__).resolve().parents[2],
                )
            )
        for trainer in trainers:
            line = trainer.stdout.readline() if trainer.stdout else ""
            if line.strip() != "ready":
                raise RuntimeError(f"trainer {trainer.pid} did not get ready: {line!r}")
        for trainer in trainers:
            assert trainer.stdin is not None
            trainer.stdin.write("go\n")
            trainer.stdin.flush()
        results = []
        for trainer in trainers:
            out, _ = trainer.communicate(timeout=config.seconds + 60)
            results.append(json.loads(out.strip().splitlines()[-1]))
    finally:
        for trainer in trainers:
            stop_process(trainer)
        stop_process(server)
    rates = [r["steps_per_s"] for r in results]
    return {"trainers": results, "min_over_max": min(rates) / max(rates), "total": sum(rates)}


def report(side: str, result: dict[str, Any]) -> None:
    print(f"{side}:")
    print("| trainer | steps/s | p50 ms | p99 ms |")
    print("|---:|---:|---:|---:|")
    for index, r in enumerate(result["trainers"]):
        print(f"| {index} | {r['steps_per_s']:.1f} | {r['p50_ms']:.2f} | {r['p99_ms']:.2f} |")
    print(
        f"slowest / fastest {result['min_over_max']:.3f}, all trainers together "
        f"{result['total']:.1f} steps/s",
        flush=True,
    )


def main(config: FairnessConfig) -> dict[str, Any]:
    print(
        f"{config.trainers} trainers x {config.arenas} arenas of {config.preset}, "
        f"{config.seconds:g} s, one server ({platform.machine()}, {os.cpu_count()} cores)",
        flush=True,
    )
    out: dict[str, Any] = {"config": {**config.__dict__, "json": None}}
    if config.baseline is not None:
        with baseline_checkout(config.baseline) as path:
            pythonpath = os.pathsep.join(p for p in (str(path), os.environ.get("PYTHONPATH")) if p)
            out["baseline"] = measure(config, {**os.environ, "PYTHONPATH": pythonpath})
        report(f"baseline {config.baseline}", out["baseline"])
    out["working tree"] = measure(config, None)
    report("working tree", out["working tree"])
    if config.json is not None:
        config.json.write_text(json.dumps(out, indent=2))
    return out


def cli() -> None:
    if len(sys.argv) > 1 and sys.argv[1] == "--trainer":
        endpoint, arenas, preset, seconds, seed = sys.argv[2:7]
        trainer_main(endpoint, int(arenas), preset, float(seconds), int(seed))
        return
    main(tyro.cli(FairnessConfig))


if __name__ == "__main__":
    cli()
