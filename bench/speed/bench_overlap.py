"""Sampling with overlap against lock-step: remote arenas driven by a Q-network acting
greedily, no learning.

One ``overtake.server`` subprocess on 127.0.0.1 (a free port) serves two vector environments
of ``--num-envs`` arenas each, open side by side: one group stepped in lock-step (the trainer
acts for all arenas, then waits for the server's round), and the same arenas as two parts
(``RemoteHighwayVectorEnv(parts=2)``: the trainer acts for one half and sends it, then takes
the other half's Steps; the server plays one half while the network runs on the other). The
network is ``overtake-train``'s (min2018's, LIDAR only by default: the camera is then not
rendered), its weights random and fixed; actions are its greedy ones, through the same
``DQNLearner.act``. The two modes run in alternating rounds (ABAB...) of ``--steps`` vector
steps each, after a warm-up, so that both see the same machine; the figure is the ratio of
their arena-steps per second, each round's ratio and the median.

With ``--in-process`` (the default) the same arenas also step in this process, lock-step, in
the same rounds, and each remote mode gets its ratio to that (the issue's "64 arenas remote"
figure, here with overlap too). ``--policy random`` drops the network: random actions, no
frame stacking, so what is measured is the simulation and its transport alone.

    .venv/bin/python -m bench.speed.bench_overlap [--num-envs 64] [--inputs lidar] [--rounds 4]
    .venv/bin/python -m bench.speed.bench_overlap --policy random --inputs both
"""

from __future__ import annotations

import statistics
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import tyro

from bench.harness import free_port, start_server, stop_process, write_report
from bench.speed.bench_sim import machine_description


@dataclass(frozen=True)
class OverlapBenchConfig:
    num_envs: int = 64
    """arenas per environment (each mode its own, on the one server)"""
    inputs: Literal["lidar", "both", "camera"] = "lidar"
    steps: int = 100
    """vector steps per timed round"""
    rounds: int = 4
    """timed rounds per mode, alternating"""
    warmup_steps: int = 20
    torch_threads: int = 1
    """PyTorch threads of this (the trainer's) process; the server runs in its own"""
    policy: Literal["network", "random"] = "network"
    """network: the Q-network acting greedily on stacked frames; random: uniformly random
    actions and no trainer work at all (what is left is the simulation and its transport)"""
    in_process: bool = True
    """also step the same arenas in this process (lock-step) and give each remote mode's
    ratio to it"""
    json: Path | None = None


def make_actor(env: Any, inputs: str, seed: int = 0) -> Any:
    """``overtake-train``'s learner (random, fixed weights) and a frame stacker for
    ``env``."""
    import torch

    from overtake.client.policies.frames import FrameStacker
    from overtake.protocol.vocabulary import ACTION_COUNT
    from overtake.trainers.learning.learner import ALGOS, DQNConfig, DQNLearner
    from overtake.trainers.learning.network import INPUT_SENSORS, NetworkShape
    from overtake.trainers.run.observations import frame_shapes

    space = env.single_observation_space
    dqn = DQNConfig()
    torch.manual_seed(seed)
    shape = NetworkShape.from_space(space, ACTION_COUNT, dqn.stack)
    learner = DQNLearner(shape, inputs, dqn, ALGOS["ddqn"], device="cpu")
    shapes = frame_shapes(space, inputs, "bench")
    stacker = FrameStacker(env.num_envs, shapes, dqn.stack, INPUT_SENSORS[inputs])
    return learner, stacker


class RandomActor:
    """Uniformly random actions, ignoring observations and masks (``policy random``)."""

    def act(self, _obs: Any, mask: np.ndarray, _epsilon: float, rng: np.random.Generator):
        return rng.integers(0, mask.shape[1], len(mask)), None


class NoStacker:
    """Keeps no frames: the random actor reads none."""

    def reset(self, _envs: np.ndarray, _obs: Any) -> None:
        pass

    def push(self, _envs: np.ndarray, _obs: Any) -> None:
        pass

    def observation(self) -> dict[str, np.ndarray]:
        return {}


def run_mode(
    env: Any, learner: Any, stacker: Any, mode: str, steps: int, rng: np.random.Generator
) -> float:
    """Arena-steps per second of ``steps`` vector steps in ``mode`` (lock-step or overlap)."""
    n = env.num_envs
    everyone = np.arange(n)
    obs, info = env.reset(seed=int(rng.integers(2**31)))
    stacker.reset(everyone, obs)
    mask = np.array(info["action_mask"])
    start = time.perf_counter()
    if mode != "overlap":  # lock-step, remote or in-process
        for _ in range(steps):
            actions, _ = learner.act(stacker.observation(), mask, 0.0, rng)
            obs, _, _, _, info = env.step(actions)
            stacker.push(everyone, obs)
            mask = info["action_mask"]
    else:
        slices = env.unwrapped.part_slices
        parts = [everyone[s] for s in slices]
        for i in range(steps * len(parts)):
            part = i % len(parts)
            rows = slices[part]
            stacked = {k: v[rows] for k, v in stacker.observation().items()}
            actions, _ = learner.act(stacked, mask[rows], 0.0, rng)
            env.unwrapped.send(part, actions)
            if i >= len(parts) - 1:
                oldest = (part + 1) % len(parts)
                obs, _, _, _, info = env.unwrapped.recv(oldest)
                stacker.push(parts[oldest], obs)
                mask[slices[oldest]] = info["action_mask"]
        for part in range(1, len(parts)):  # still in flight: every part but the first
            env.unwrapped.recv(part)
    return n * steps / (time.perf_counter() - start)


def main(config: OverlapBenchConfig) -> dict[str, Any]:
    import gymnasium as gym
    import torch

    from overtake.client.wire.remote import RemoteConfig
    from overtake.envs import HIGHWAY_ENV_ID, REMOTE_HIGHWAY_ENV_ID, register_environments
    from overtake.trainers.train import TrainConfig

    torch.set_num_threads(config.torch_threads)
    register_environments()
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    server = start_server(endpoint, 60.0)
    envs: dict[str, Any] = {}
    # overtake-train's: only the sensors the network reads (no camera for a LIDAR-only one)
    train = TrainConfig(inputs=config.inputs)
    overrides, observations = train.overrides(), train.observations
    try:
        if config.in_process:
            envs["in-process"] = gym.make_vec(
                HIGHWAY_ENV_ID,
                num_envs=config.num_envs,
                vectorization_mode="vector_entry_point",
                overrides=overrides,
                observations=observations,
            )
        for mode, parts in (("lock-step", 1), ("overlap", 2)):
            envs[mode] = gym.make_vec(
                REMOTE_HIGHWAY_ENV_ID,
                num_envs=config.num_envs,
                vectorization_mode="vector_entry_point",
                remote=RemoteConfig(connect=(endpoint,)),
                overrides=overrides,
                observations=observations,
                parts=parts,
            )
        rng = np.random.default_rng(0)
        actor = (
            make_actor(envs["lock-step"], config.inputs)
            if config.policy == "network"
            else (RandomActor(), NoStacker())
        )
        for mode, env in envs.items():
            run_mode(env, *actor, mode, config.warmup_steps, rng)
        rates: dict[str, list[float]] = {mode: [] for mode in envs}
        for _ in range(config.rounds):
            for mode, env in envs.items():
                rates[mode].append(run_mode(env, *actor, mode, config.steps, rng))
    finally:
        for env in envs.values():
            env.close()
        stop_process(server)
    ratios = [o / lock for o, lock in zip(rates["overlap"], rates["lock-step"], strict=True)]
    report = {
        "config": {k: str(v) for k, v in vars(config).items()},
        "machine": machine_description(),
        "arena_steps_per_s": {m: [round(r, 1) for r in v] for m, v in rates.items()},
        "overlap_over_lock_step": [round(r, 3) for r in ratios],
        "median_ratio": round(statistics.median(ratios), 3),
    }
    if config.in_process:
        report["over_in_process"] = {
            mode: round(
                statistics.median(
                    r / local for r, local in zip(rates[mode], rates["in-process"], strict=True)
                ),
                3,
            )
            for mode in ("lock-step", "overlap")
        }
    acting = (
        f"{config.inputs} network acting greedily"
        if config.policy == "network"
        else "random actions"
    )
    print(
        f"{config.num_envs} arenas, {acting}, "
        f"{config.rounds} rounds of {config.steps} vector steps per mode"
    )
    for mode, values in rates.items():
        print(f"  {mode:>10}: {statistics.median(values):8.1f} arena-steps/s (median)")
    print(f"  overlap / lock-step: {report['median_ratio']:.2f}x (rounds: {ratios})")
    if config.in_process:
        print(f"  remote / in-process (median of rounds): {report['over_in_process']}")
    write_report(config.json, report)
    return report


if __name__ == "__main__":
    main(tyro.cli(OverlapBenchConfig))
