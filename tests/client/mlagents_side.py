"""ML-Agents' side of tests/client/test_unity_bridge.py: mlagents-envs 1.1.0's own
``UnityEnvironment`` (and ``UnityToGymWrapper``), run in .venv-mlagents (protobuf 3.20;
scripts/setup-mlagents.sh), listening on a port for overtake-unity-bridge as it would for a Unity
scene.

    .venv-mlagents/bin/python tests/client/mlagents_side.py SCENARIO PORT [STEPS]

It prints one JSON line of what it saw; a failure prints {"error": type, "message": ...,
"after_s": seconds} and exits 0, so the test reads what ML-Agents raised.
Scenarios: steps (specs, resets, random steps, environment parameters), gym (UnityToGymWrapper),
hang (reset, then wait while the test kills the bridge; step must fail within timeout_wait),
version (claims communication version 2.0.0).
"""

from __future__ import annotations

import importlib
import json
import os
import sys
import time
import traceback
import types
from pathlib import Path

import numpy as np
from mlagents_envs.base_env import ActionTuple
from mlagents_envs.environment import UnityEnvironment
from mlagents_envs.side_channel.environment_parameters_channel import (
    EnvironmentParametersChannel,
)


def first_obs(env: UnityEnvironment, name: str) -> dict[str, list]:
    decision, _ = env.get_steps(name)
    spec = env.behavior_specs[name]
    return {o.name: obs[0].ravel().tolist() for o, obs in zip(spec.observation_specs, decision.obs)}


def steps(port: int, count: int) -> dict:
    parameters = EnvironmentParametersChannel()
    env = UnityEnvironment(
        file_name=None, base_port=port, seed=7, timeout_wait=30, side_channels=[parameters]
    )
    env.reset()
    name = next(iter(env.behavior_specs))
    spec = env.behavior_specs[name]
    out: dict = {
        "behaviors": list(env.behavior_specs),
        "observations": [
            [o.name, list(o.shape), [int(p) for p in o.dimension_property]]
            for o in spec.observation_specs
        ],
        "branches": list(spec.action_spec.discrete_branches),
        "continuous": spec.action_spec.continuous_size,
        "first": first_obs(env, name),
        "agents_at_reset": sorted(int(a) for a in env.get_steps(name)[0].agent_id),
    }
    rng = np.random.default_rng(0)
    terminal_ids, interrupted, masks_ok = [], [], True
    for _ in range(count):
        decision, terminal = env.get_steps(name)
        terminal_ids += [int(a) for a in terminal.agent_id]
        interrupted += [bool(i) for i in terminal.interrupted]
        if len(decision) == 0:
            # Every agent ended this step (overtake's agents decide again after the next
            # one): ML-Agents then has no masks, and steps with no actions.
            env.step()
            continue
        mask = decision.action_mask[0]
        masks_ok &= mask.shape == (len(decision), 5) and bool((~mask).any(axis=1).all())
        # Only allowed actions, as a trainer reading the masks would choose.
        choice = np.array(
            [rng.choice(np.flatnonzero(~row)) for row in mask], dtype=np.int32
        ).reshape(-1, 1)
        env.set_actions(name, ActionTuple(discrete=choice))
        env.step()
    out.update(terminal_ids=terminal_ids, interrupted=interrupted, masks_ok=masks_ok)
    # A second reset: new seeds, so another first observation.
    env.reset()
    out["first_after_second_reset"] = first_obs(env, name)
    parameters.set_float_parameter("traffic.vehicle_count", 3)
    env.reset()
    decision, _ = env.get_steps(name)
    out["agents_after_parameters"] = len(decision)
    env.close()
    return out


def load_gym_wrapper():
    """UnityToGymWrapper without mlagents_envs.envs.__init__ (it downloads a registry)."""
    import mlagents_envs

    folder = Path(mlagents_envs.__file__).parent / "envs"
    stand_in = types.ModuleType("mlagents_envs.envs")
    stand_in.__path__ = [str(folder)]
    sys.modules["mlagents_envs.envs"] = stand_in
    return importlib.import_module("mlagents_envs.envs.unity_gym_env").UnityToGymWrapper


def gym(port: int, count: int) -> dict:
    wrapper = load_gym_wrapper()
    env = wrapper(
        UnityEnvironment(file_name=None, base_port=port, seed=3, timeout_wait=30),
        allow_multiple_obs=True,
    )
    obs = env.reset()
    out = {
        "action_space": str(env.action_space),
        "obs_shapes": [list(o.shape) for o in obs],
        "space_shapes": [list(s.shape) for s in env.observation_space.spaces],
    }
    dones, rewards = 0, []
    for i in range(count):
        obs, reward, done, _info = env.step(i % 5)
        rewards.append(float(reward))
        if done:
            dones += 1
            obs = env.reset()
    out.update(dones=dones, rewards=len(rewards), finite=bool(np.isfinite(rewards).all()))
    env.close()
    return out


def hang(port: int, _count: int) -> dict:
    env = UnityEnvironment(file_name=None, base_port=port, seed=1, timeout_wait=6)
    env.reset()
    name = next(iter(env.behavior_specs))
    print(json.dumps({"ready": True}), flush=True)
    sys.stdin.readline()  # the test kills the bridge, then writes a line
    started = time.monotonic()
    try:
        for _ in range(5):
            env.set_actions(name, ActionTuple(discrete=np.zeros((1, 1), dtype=np.int32)))
            env.step()
    except Exception as error:  # what ML-Agents raises when its "Unity" is gone
        return {
            "error": type(error).__name__,
            "message": str(error),
            "after_s": time.monotonic() - started,
        }
    return {"after_s": time.monotonic() - started, "stepped": True}


def version(port: int, _count: int) -> dict:
    UnityEnvironment.API_VERSION = "2.0.0"
    env = UnityEnvironment(file_name=None, base_port=port, seed=1, timeout_wait=20)
    env.close()
    return {"connected": True}


SCENARIOS = {"steps": steps, "gym": gym, "hang": hang, "version": version}


def main() -> None:
    scenario, port = sys.argv[1], int(sys.argv[2])
    count = int(sys.argv[3]) if len(sys.argv) > 3 else 0
    started = time.monotonic()
    try:
        result = SCENARIOS[scenario](port, count)
    except Exception as error:  # reported to the test, which asserts on it
        result = {
            "error": type(error).__name__,
            "message": str(error),
            "after_s": time.monotonic() - started,
            "where": traceback.format_exc()[-1500:],
        }
    print(json.dumps(result), flush=True)
    # Not through the interpreter's exit: ML-Agents' atexit close and gRPC's threads can wait
    # on a peer that is gone; what this process had to say is said.
    os._exit(0)


if __name__ == "__main__":
    main()
