"""Stable-Baselines3's DQN on overtake, in process or on a simulator server.

    python examples/sb3_dqn.py                                   # overtake/Highway-v0
    python examples/sb3_dqn.py --connect tcp/127.0.0.1:7447      # overtake/RemoteHighway-v0
    python examples/sb3_dqn.py --total-timesteps 200000 --save runs/sb3-dqn.zip

SB3's ``MultiInputPolicy`` takes overtake's Dict observation as it is. Its combined feature
extractor sends images (uint8, channels first or last) through a CNN and flattens every other
key; overtake's grey camera is a 2-D (80, 80) array, so this example gives it a channel axis
(a standard Gymnasium wrapper) and SB3 treats it as the image it is. The LIDAR and ego vector
go in as vectors. SB3 does not apply overtake's action mask: a lateral action that cannot be
taken is simply ignored by the simulator (``info["action_applied"]`` says so).

Needs ``pip install -e ".[examples]"`` (stable-baselines3).
"""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym
import numpy as np
import tyro
from stable_baselines3 import DQN
from stable_baselines3.common.evaluation import evaluate_policy
from stable_baselines3.common.logger import HumanOutputFormat, Logger
from stable_baselines3.common.monitor import Monitor

import overtake.client  # noqa: F401  (registers overtake/Highway-v0 and RemoteHighway-v0)
from overtake.client.episodes.scenario import parse_overrides


@dataclass(frozen=True)
class Args:
    preset: str = "min2018"
    """the simulator preset (min2018, ho2018, fayjie2018; highway-env's scenes, highway-fast and
    highway, have their own recipe: docs/highway-env.md)"""
    connect: str | None = None
    """a simulator server's Zenoh endpoint; None runs the simulator in this process"""
    set: tuple[str, ...] = ()
    """simulator overrides, dotted.name=value (e.g. --set traffic.density=heavy)"""
    total_timesteps: int = 50_000
    learning_starts: int = 1_000
    buffer_size: int = 50_000
    seed: int = 0
    eval_episodes: int = 2
    """greedy episodes after training; 0 skips the evaluation"""
    save: Path | None = None
    """where to save the trained model (SB3's .zip)"""


def with_image_channel(env: gym.Env) -> gym.Env:
    """Give every 2-D uint8 observation (a grey camera, a grid) a trailing channel axis, so that
    SB3's CNN takes it as an image (SB3 wants images with 1 or 3 channels)."""
    space = env.observation_space
    assert isinstance(space, gym.spaces.Dict)
    flat = [k for k, s in space.spaces.items() if s.dtype == np.uint8 and len(s.shape) == 2]
    if not flat:
        return env
    new_space = gym.spaces.Dict(
        {
            k: gym.spaces.Box(
                low=s.low[..., None], high=s.high[..., None], shape=(*s.shape, 1), dtype=s.dtype
            )
            if k in flat
            else s
            for k, s in space.spaces.items()
        }
    )
    return gym.wrappers.TransformObservation(
        env, lambda obs: {k: v[..., None] if k in flat else v for k, v in obs.items()}, new_space
    )


def make_env(args: Args) -> gym.Env:
    overrides = parse_overrides(args.set)
    if args.connect is None:
        env = gym.make("overtake/Highway-v0", preset=args.preset, overrides=overrides)
    else:
        env = gym.make(
            "overtake/RemoteHighway-v0",
            connect=args.connect,
            preset=args.preset,
            overrides=overrides,
        )
    return Monitor(with_image_channel(env))  # episode returns as SB3 reports them


def main(args: Args) -> tuple[float, float]:
    """Train, then evaluate greedily; returns the evaluation's mean and spread of returns."""
    env = make_env(args)
    try:
        model = DQN(
            "MultiInputPolicy",
            env,
            learning_starts=args.learning_starts,
            buffer_size=args.buffer_size,
            seed=args.seed,
            verbose=0,
        )
        # SB3's default logger makes an SB3-<date> folder in the temporary directory, empty
        # with verbose=0: one that prints its tables (every 4 episodes) and makes nothing.
        model.set_logger(Logger(folder=None, output_formats=[HumanOutputFormat(sys.stdout)]))
        model.learn(total_timesteps=args.total_timesteps)
        if args.save is not None:
            args.save.parent.mkdir(parents=True, exist_ok=True)
            model.save(args.save)
        if args.eval_episodes == 0:
            return float("nan"), float("nan")
        mean, spread = evaluate_policy(model, env, n_eval_episodes=args.eval_episodes)
        print(f"greedy return over {args.eval_episodes} episode(s): {mean:.2f} ± {spread:.2f}")
        return float(mean), float(spread)
    finally:
        env.close()


if __name__ == "__main__":
    main(tyro.cli(Args))
