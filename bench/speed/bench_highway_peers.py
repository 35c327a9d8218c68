"""Speed on highway-env's own scene: overtake's ``overtake/highway-fast-v0`` against EnvPool
1.2.5's C++ ``HighwayFast-v0`` and highway-env 1.12.1's ``highway-fast-v0`` (issue 58).

Each peer steps uniformly random actions (seeded) with resets included, in batches of 1, 64
and 256 environments; each measurement is taken ``--rounds`` times, the peers alternating, and
the better of each kept. Reported: agent-steps per CPU second (``time.process_time`` of this
process, every thread counted) and per wall second. EnvPool runs one thread per core it may
use (``num_threads``, at most the batch); overtake steps in this one thread; highway-env one
environment only (a batch is a loop of them, no faster per step).

Run with nothing else on the machine (pause long runs)::

    .venv/bin/python -m bench.speed.bench_highway_peers --out runs/bench/highway-peers.json
"""

from __future__ import annotations

import json
import os
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

Stepper = tuple[Callable[[], Any], Callable[[np.ndarray], Any], int]


@dataclass(frozen=True)
class PeersConfig:
    """overtake, EnvPool and highway-env on highway-fast-v0's scene, agent-steps per second."""

    batches: tuple[int, ...] = (1, 64, 256)
    steps: int = 4_000
    """agent-steps timed per measurement (at least one step of the batch)"""
    rounds: int = 2
    highway_env_steps: int = 300
    out: Path | None = None


def single_stepper(env: Any) -> Stepper:
    """One environment, reset where its episode ends (a batch of 1)."""

    def step(action: np.ndarray) -> Any:
        _, _, terminated, truncated, _ = env.step(int(action[0]))
        if terminated or truncated:
            env.reset()

    return (lambda: env.reset(seed=0)), step, 1


def overtake_stepper(batch: int) -> Stepper:
    import gymnasium as gym

    import overtake.client  # noqa: F401

    if batch == 1:
        return single_stepper(gym.make("overtake/highway-fast-v0"))
    envs = gym.make_vec("overtake/highway-fast-v0", num_envs=batch)
    return (lambda: envs.reset(seed=0)), envs.step, batch


def envpool_stepper(batch: int) -> Stepper:
    import envpool

    threads = min(batch, os.cpu_count() or 1)
    env = envpool.make_gym("HighwayFast-v0", num_envs=batch, batch_size=batch, num_threads=threads)
    return (lambda: env.reset()), env.step, batch


def highway_env_stepper(batch: int) -> Stepper:
    import gymnasium as gym
    import highway_env  # noqa: F401

    return single_stepper(gym.make("highway-fast-v0"))


PEERS = {
    "overtake": overtake_stepper,
    "envpool": envpool_stepper,
    "highway-env": highway_env_stepper,
}


def measure(stepper: Stepper, agent_steps: int) -> dict[str, float]:
    reset, step, batch = stepper
    reset()
    rng = np.random.default_rng(0)
    rounds = max(1, agent_steps // batch)
    actions = rng.integers(0, 5, (rounds + 20, batch))
    for i in range(20):  # warm-up (compiled loops, caches)
        step(actions[i])
    cpu, wall = time.process_time(), time.perf_counter()
    for i in range(rounds):
        step(actions[20 + i])
    cpu, wall = time.process_time() - cpu, time.perf_counter() - wall
    return {"per_cpu_s": rounds * batch / cpu, "per_wall_s": rounds * batch / wall}


def main(config: PeersConfig) -> dict[str, Any]:
    results: dict[str, Any] = {}
    for batch in config.batches:
        peers = [p for p in PEERS if p != "highway-env" or batch == 1]
        steppers = {peer: PEERS[peer](batch) for peer in peers}
        best: dict[str, dict[str, float]] = {peer: {} for peer in peers}
        for _ in range(config.rounds):  # the peers in turn, every round
            for peer, stepper in steppers.items():
                steps = config.highway_env_steps if peer == "highway-env" else config.steps
                got = measure(stepper, max(steps, batch * 20))
                best[peer] = {k: max(best[peer].get(k, 0.0), v) for k, v in got.items()}
        results[str(batch)] = best
        for peer, figures in best.items():
            print(f"batch {batch:4d} {peer:12s} {figures['per_cpu_s']:10,.0f} /CPU-s "
                  f"{figures['per_wall_s']:10,.0f} /wall-s", flush=True)  # fmt: skip
    for row in results.values():
        if "envpool" in row:
            row["overtake_over_envpool_cpu"] = (
                row["overtake"]["per_cpu_s"] / row["envpool"]["per_cpu_s"]
            )
            row["overtake_over_envpool_wall"] = (
                row["overtake"]["per_wall_s"] / row["envpool"]["per_wall_s"]
            )
    if config.out is not None:
        config.out.parent.mkdir(parents=True, exist_ok=True)
        config.out.write_text(json.dumps(results, indent=1))
    return results


if __name__ == "__main__":
    import tyro

    main(tyro.cli(PeersConfig))
