"""A/B of two versions of the server: remote step latency against each, measured together.

On a shared 2-vCPU VM the remote step's median drifts by 10-20% between runs of the same code,
so a change worth a few per cent cannot be seen by comparing two runs. Here one process steps
two single-arena remote environments, one against a server running the working tree's code and
one against a server running another git revision's (checked out in a temporary worktree and
put first on that server's PYTHONPATH), in alternating chunks with the order flipped every
round: both see the same drift. The client is this process's code for both.

    .venv/bin/python -m bench.speed.bench_server_ab --baseline REV [--rounds 30] [--repeats 3]

Each repeat starts both servers afresh and prints both medians and their difference
(baseline - working tree: positive when the working tree is faster).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import tyro

from bench.harness import (
    REMOTE_ENV_ID,
    baseline_checkout,
    free_port,
    make_env,
    start_server,
    stop_process,
    write_report,
)
from bench.speed.bench_remote import Driver

SIDES = ("baseline", "working tree")


@dataclass(frozen=True)
class ServerABConfig:
    baseline: str
    """The git revision whose server is compared with the working tree's."""
    rounds: int = 30
    """Alternating chunks per server and repeat."""
    chunk: int = 200
    """Steps per chunk."""
    warmup_steps: int = 200
    repeats: int = 3
    preset: str = "min2018"
    seed: int = 0
    json: Path | None = None


def measure(config: ServerABConfig, baseline_path: Path) -> dict[str, Any]:
    import numpy as np

    from overtake.client.wire.remote import RemoteConfig

    endpoints = {side: f"tcp/127.0.0.1:{free_port()}" for side in SIDES}
    # The baseline's server finds that revision's overtake first on its path.
    path = os.pathsep.join(p for p in (str(baseline_path), os.environ.get("PYTHONPATH")) if p)
    environments = {"baseline": {**os.environ, "PYTHONPATH": path}, "working tree": None}
    servers: dict[str, Any] = {}
    drivers: dict[str, Driver] = {}
    try:
        for side in SIDES:
            servers[side] = start_server(endpoints[side], 60.0, env=environments[side])
            drivers[side] = Driver(
                make_env(
                    REMOTE_ENV_ID,
                    1,
                    preset=config.preset,
                    remote=RemoteConfig(connect=(endpoints[side],)),
                ),
                arenas=1,
                seed=config.seed,
                vector=False,
            )
        for driver in drivers.values():
            driver.drive(config.warmup_steps, timed=False)
        for index in range(config.rounds):
            for side in SIDES if index % 2 == 0 else SIDES[::-1]:
                drivers[side].drive(config.chunk)
    finally:
        for driver in drivers.values():
            driver.env.close()
        for server in servers.values():
            stop_process(server)
    p50 = {side: float(np.median(d.step_times) * 1e3) for side, d in drivers.items()}
    return {
        "p50_ms": p50,
        "steps": drivers["baseline"].steps,
        "baseline_minus_working_tree_ms": p50["baseline"] - p50["working tree"],
    }


def main(config: ServerABConfig) -> dict[str, Any]:
    results = []
    with baseline_checkout(config.baseline) as baseline_path:
        for repeat in range(config.repeats):
            result = measure(config, baseline_path)
            results.append(result)
            print(
                f"repeat {repeat + 1}: baseline {result['p50_ms']['baseline']:.3f} ms, "
                f"working tree {result['p50_ms']['working tree']:.3f} ms (p50 of "
                f"{result['steps']} steps each): "
                f"{1e3 * result['baseline_minus_working_tree_ms']:+.1f} us",
                flush=True,
            )
    differences = sorted(r["baseline_minus_working_tree_ms"] for r in results)
    print(
        f"median difference {1e3 * differences[len(differences) // 2]:+.1f} us "
        f"(baseline - working tree; from {1e3 * differences[0]:+.1f} to "
        f"{1e3 * differences[-1]:+.1f})"
    )
    report = {
        "config": {**config.__dict__, "json": None if config.json is None else str(config.json)},
        "results": results,
    }
    write_report(config.json, report)
    return report


def cli() -> None:
    main(tyro.cli(ServerABConfig, description=__doc__))


if __name__ == "__main__":
    cli()
