"""ML-Agents' side of bench/speed/bench_unity_bridge.py, run in .venv-mlagents (mlagents-envs 1.1.0,
protobuf 3.20): ``UnityEnvironment(file_name=None, base_port=PORT)`` stepped with random
allowed actions; prints one JSON line with the timed steps per second.

    .venv-mlagents/bin/python bench/speed/mlagents_driver.py PORT WARMUP STEPS
"""

from __future__ import annotations

import json
import os
import sys
import time

import numpy as np
from mlagents_envs.base_env import ActionTuple
from mlagents_envs.environment import UnityEnvironment


def drive(env: UnityEnvironment, name: str, steps: int, rng: np.random.Generator) -> int:
    """``steps`` decisions of random allowed actions; returns the agent-decisions made."""
    decisions = 0
    for _ in range(steps):
        decision, _ = env.get_steps(name)
        if len(decision):
            mask = decision.action_mask[0]
            choice = [rng.choice(np.flatnonzero(~row)) for row in mask]
            env.set_actions(
                name, ActionTuple(discrete=np.array(choice, dtype=np.int32).reshape(-1, 1))
            )
            decisions += len(decision)
        env.step()
    return decisions


def main() -> None:
    port, warmup, steps = (int(a) for a in sys.argv[1:4])
    env = UnityEnvironment(file_name=None, base_port=port, seed=0, timeout_wait=60)
    env.reset()
    name = next(iter(env.behavior_specs))
    rng = np.random.default_rng(0)
    drive(env, name, warmup, rng)
    started = time.perf_counter()
    decisions = drive(env, name, steps, rng)
    elapsed = time.perf_counter() - started
    env.close()
    print(json.dumps({"steps_per_s": steps / elapsed, "decisions": decisions}), flush=True)
    os._exit(0)  # not through ML-Agents' atexit close of a peer that has gone


if __name__ == "__main__":
    main()
