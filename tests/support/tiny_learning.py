"""What the trainers' tests (tests/trainers) learn on: purpose-built tiny environments (one the
learner learns, one that watches a single environment), a tiny DQN configuration and its
greedy score, and small networks, observations and batches.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from overtake.trainers.learning.learner import DQNConfig
from overtake.trainers.learning.network import NetworkShape
from overtake.trainers.learning.replay_memory import ReplayBatch
from overtake.trainers.run.checkpoint import load_checkpoint

# --- small networks, observations and batches -----------------------------------------------


def small_shape(**changes: Any) -> NetworkShape:
    shape = NetworkShape(
        camera_hw=(36, 36),
        lidar_rays=8,
        ego_size=6,
        actions=5,
        stack=4,
        lidar_max_m=80.0,
        ego_high=(100.0, 22.2, 4.0, 12.0, 1.0, 1.0),
    )
    return replace(shape, **changes)


def random_obs(shape: NetworkShape, batch: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    return {
        "camera": rng.integers(0, 256, (batch, shape.stack) + shape.camera_hw, dtype=np.uint8),
        "lidar": rng.uniform(0, 80, (batch, shape.stack, shape.lidar_rays)).astype(np.float32),
        "ego": rng.uniform(0, 1, (batch, shape.ego_size)).astype(np.float32),
    }


def reward_three_for_action_two(obs: dict[str, np.ndarray]) -> ReplayBatch:
    """A replay batch of 32 one-step episodes: action 2 taken, reward 3, nothing after (with
    gamma 0, Q of action 2 should go to 3)."""
    return ReplayBatch(
        obs=obs,
        next_obs=obs,
        action=np.full(32, 2),
        reward=np.full(32, 3.0, dtype=np.float32),
        terminated=np.zeros(32, dtype=bool),
        steps=np.ones(32, dtype=np.int64),
        next_mask=np.ones((32, 5), np.int8),
    )


# --- a purpose-built tiny environment: the learner learns ----------------------------------------


class PickTheFreeLane(gym.vector.VectorEnv):
    """Each decision the LIDAR shows five distances; driving towards the largest pays 1.

    Random scores 0.2 a decision; a policy that reads its newest scan scores 1. Episodes of
    ``length`` decisions, Gymnasium next-step autoreset, overtake's observation keys.
    """

    metadata = {"autoreset_mode": gym.vector.AutoresetMode.NEXT_STEP}  # noqa: RUF012

    def __init__(self, num_envs: int, length: int = 16, seed: int = 0) -> None:
        self.num_envs, self.length = num_envs, length
        self.single_observation_space = spaces.Dict(
            {
                "ego": spaces.Box(-1.0, 1.0, (6,), np.float32),
                "lidar": spaces.Box(0.0, 80.0, (5,), np.float32),
            }
        )
        self.single_action_space = spaces.Discrete(5)
        self.observation_space = gym.vector.utils.batch_space(
            self.single_observation_space, num_envs
        )
        self.action_space = spaces.MultiDiscrete(np.full(num_envs, 5))
        self.rng = np.random.default_rng(seed)
        self.t = np.zeros(num_envs, dtype=int)
        self.total = np.zeros(num_envs)
        self.autoreset = np.zeros(num_envs, dtype=bool)

    def _obs(self):
        self.lidar = self.rng.uniform(0.0, 80.0, (self.num_envs, 5)).astype(np.float32)
        return {"ego": np.zeros((self.num_envs, 6), np.float32), "lidar": self.lidar.copy()}

    def _info(self):
        return {"action_mask": np.ones((self.num_envs, 5), np.int8)}

    def reset(self, *, seed=None, options=None):
        self.t[:] = 0
        self.total[:] = 0
        self.autoreset[:] = False
        return self._obs(), self._info()

    def step(self, actions):
        reward = (np.asarray(actions) == self.lidar.argmax(axis=1)).astype(float)
        reward[self.autoreset] = 0.0
        self.t = np.where(self.autoreset, 0, self.t + 1)
        self.total = np.where(self.autoreset, 0.0, self.total + reward)
        truncated = self.t >= self.length
        info = self._info()
        if truncated.any():
            info["metrics"] = {
                "return": np.where(truncated, self.total, 0.0),
                "avg_speed_kmh": np.zeros(self.num_envs),
            }
            info["_metrics"] = truncated
        self.autoreset = truncated
        return self._obs(), reward, np.zeros(self.num_envs, bool), truncated, info


class WatchEnvZero(gym.vector.VectorEnv):
    """Passes everything through, keeping per step environment 0's LIDAR before the step, its
    action, its reward, and whether the step was its autoreset."""

    def __init__(self, env: gym.vector.VectorEnv) -> None:
        self.env = env
        self.metadata = env.metadata
        self.num_envs = env.num_envs
        self.single_observation_space = env.single_observation_space
        self.single_action_space = env.single_action_space
        self.observation_space, self.action_space = env.observation_space, env.action_space
        self.log: list[tuple[np.ndarray, int, float, bool]] = []
        self._last, self._resetting = None, False

    def reset(self, *, seed=None, options=None):
        obs, info = self.env.reset(seed=seed, options=options)
        self._last, self._resetting = obs["lidar"][0].copy(), False
        return obs, info

    def step(self, actions):
        obs, reward, terminated, truncated, info = self.env.step(actions)
        self.log.append((self._last, int(actions[0]), float(reward[0]), self._resetting))
        self._last = obs["lidar"][0].copy()
        self._resetting = bool(terminated[0] or truncated[0])
        return obs, reward, terminated, truncated, info


def tiny_dqn(**changes: Any) -> DQNConfig:
    settings = dict(
        learning_rate=0.002,
        batch_size=32,
        replay_size=4000,
        learning_starts=300,
        gamma=0.5,
        epsilon_decay_steps=1500,
        epsilon_end=0.05,
        target_update_steps=200,
        train_every=1,
        lstm_cells=32,
        hidden_units=64,
    )
    settings.update(changes)
    return DQNConfig(**settings)


def greedy_score(checkpoint_path: Path, episodes: int = 200) -> float:
    checkpoint = load_checkpoint(checkpoint_path)
    learner = checkpoint.make_learner()
    env = PickTheFreeLane(episodes, seed=99)
    obs, info = env.reset()
    stack = np.repeat(obs["lidar"][:, None], checkpoint.dqn.stack, axis=1)
    actions, _ = learner.act(
        {"lidar": stack, "ego": obs["ego"]}, info["action_mask"], 0.0, np.random.default_rng(0)
    )
    _, reward, *_ = env.step(actions)
    return float(reward.mean())
