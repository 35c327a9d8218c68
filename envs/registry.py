"""The Gymnasium ids of overtake's environments, registered with string entry points.

``import overtake.client`` calls :func:`register_environments` (and so does
``gym.make("overtake.client:overtake/Highway-v0")``); the entry points are strings, so
registering never imports the simulator into a trainer. The helpers below are what the
in-process and the remote environments share: how a seed spreads over arenas, how actions are
checked, and how the episode length is reported.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np

from overtake.protocol.vocabulary import ACTION_COUNT, ACTION_NAMES

HIGHWAY_ENV_ID = "overtake/Highway-v0"
REMOTE_HIGHWAY_ENV_ID = "overtake/RemoteHighway-v0"
# highway-env's own scenes with highway-env's interface (overtake.envs.highway_env_like).
HIGHWAY_ENV_LIKE_IDS = {
    "overtake/highway-fast-v0": "highway-fast",
    "overtake/highway-v0": "highway",
}


def register_environments() -> None:
    """Register the environments once (idempotent)."""
    if HIGHWAY_ENV_ID not in gym.registry:
        gym.register(
            id=HIGHWAY_ENV_ID,
            entry_point="overtake.server.engine.env:HighwayEnv",
            vector_entry_point="overtake.server.engine.env:HighwayVectorEnv",
            # The environment truncates itself at its preset's episode length, which a user may
            # override; a TimeLimit fixed here could not follow it. env.spec reports it.
            max_episode_steps=None,
        )
    for env_id, preset in HIGHWAY_ENV_LIKE_IDS.items():
        if env_id not in gym.registry:
            gym.register(
                id=env_id,
                entry_point="overtake.envs.highway_env_like:HighwayEnvLike",
                vector_entry_point="overtake.envs.highway_env_like:HighwayEnvLikeVector",
                kwargs={"scene": preset},
                max_episode_steps=None,
            )
    if REMOTE_HIGHWAY_ENV_ID not in gym.registry:
        gym.register(
            id=REMOTE_HIGHWAY_ENV_ID,
            entry_point="overtake.client.envs.remote_gym:RemoteHighwayEnv",
            vector_entry_point="overtake.client.envs.remote_gym:RemoteHighwayVectorEnv",
            max_episode_steps=None,
        )


def arena_seeds(seed: int | Sequence[int | None] | None, count: int) -> list[int | None]:
    """One seed per arena, as every overtake vector env and arena group reads ``seed``.

    None: fresh entropy everywhere; an int: arena ``i`` gets ``seed + i``; a sequence: one
    each (its length must be ``count``).
    """
    if seed is None:
        return [None] * count
    if isinstance(seed, (int, np.integer)):
        return [int(seed) + i for i in range(count)]
    seeds = [None if s is None else int(s) for s in seed]
    if len(seeds) != count:
        raise ValueError(f"expected {count} seeds (one per arena), got {len(seeds)}")
    return seeds


class ReportsEpisodeLength:
    """Mixed into an environment that truncates itself at ``max_episode_steps``.

    ``gym.make`` sets ``env.spec`` after construction; the spec then reports the preset's own
    episode length, which a user may override (a TimeLimit fixed at registration could not
    follow it, so none is added).
    """

    max_episode_steps: int
    _spec: gym.envs.registration.EnvSpec | None = None

    @property
    def spec(self) -> gym.envs.registration.EnvSpec | None:
        return self._spec

    @spec.setter
    def spec(self, value: gym.envs.registration.EnvSpec | None) -> None:
        self._spec = (
            None
            if value is None
            else dataclasses.replace(value, max_episode_steps=self.max_episode_steps)
        )


def check_actions(actions: Any, count: int, *, single: bool) -> np.ndarray:
    """Integer actions in [0, ACTION_COUNT) as an int64 array of ``count``.

    ``single``: a single environment, whose one action may be a plain integer.
    """
    if single and isinstance(actions, (int, np.integer)) and 0 <= actions < ACTION_COUNT:
        return np.array([actions], dtype=np.int64)  # the single env's common case, cheaply
    values = np.asarray(actions)
    if single and values.size == 1 and values.ndim <= 2:
        values = values.reshape(1)  # 3, [3] and [[3]] all mean action 3
    if values.shape != (count,) or not np.issubdtype(values.dtype, np.integer):
        wanted = "an integer action" if single else f"integer actions of shape ({count},)"
        raise ValueError(f"expected {wanted} in [0, {ACTION_COUNT}), got {actions!r}")
    if values.size and (values.min() < 0 or values.max() >= ACTION_COUNT):
        raise ValueError(
            f"actions must be in [0, {ACTION_COUNT}) ({', '.join(ACTION_NAMES)}), "
            f"got {values.tolist()}"
        )
    return values.astype(np.int64)


def check_render_mode(render_mode: str | None, modes: Sequence[str]) -> None:
    """Refuse a render mode the environment has not got, naming those it has; an environment
    with none is remote, and its world is watched with a spectator instead."""
    if render_mode is None or render_mode in modes:
        return
    if not modes:
        raise ValueError(
            "the remote environment does not render; watch it with a spectator "
            f"(render_mode must be None, got {render_mode!r})"
        )
    raise ValueError(f"render_mode must be one of {list(modes)} or None, got {render_mode!r}")
