"""The Gymnasium ids of overtake's environments, registered with string entry points.

``import overtake.client`` calls :func:`register_environments` (and so does
``gym.make("overtake.client:overtake/Highway-v0")``); the entry points are strings, so
registering never imports the simulator into a trainer. The helpers below are what the
in-process and the remote environments share: how a seed spreads over arenas, how actions are
checked, and how the episode length is reported.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import gymnasium as gym
import numpy as np

from .vocabulary import ACTION_COUNT, ACTION_NAMES

HIGHWAY_ENV_ID = "overtake/Highway-v0"
REMOTE_HIGHWAY_ENV_ID = "overtake/RemoteHighway-v0"


def register_environments() -> None:
    """Register the environments once (idempotent)."""
    if HIGHWAY_ENV_ID not in gym.registry:
        gym.register(
            id=HIGHWAY_ENV_ID,
            entry_point="overtake.server.env:HighwayEnv",
            vector_entry_point="overtake.server.env:HighwayVectorEnv",
            # The environment truncates itself at its preset's episode length, which a user may
            # override; a TimeLimit fixed here could not follow it. env.spec reports it.
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


# --- PettingZoo's Parallel API: several learning cars on one road -----------------------------


def agent_names(count: int) -> list[str]:
    """The PettingZoo agent names of a road with ``count`` learning cars: car_0, car_1, ..."""
    return [f"car_{i}" for i in range(count)]


class ParallelAgents:
    """The agents of a shared road as PettingZoo's Parallel API names them, and their spaces:
    one observation and one action space object for every agent (PettingZoo's API test checks
    that an agent gets the same object every time), and a clear error for a name that is not
    on this road. Both the in-process and the remote ParallelEnv are built on it."""

    possible_agents: list[str]

    def _init_agents(self, count: int, observation_space: gym.spaces.Dict) -> None:
        self.possible_agents = agent_names(count)
        self.agents: list[str] = []
        self._index = {name: i for i, name in enumerate(self.possible_agents)}
        self._observation_space = observation_space
        self._action_space: gym.spaces.Discrete = gym.spaces.Discrete(ACTION_COUNT)

    def observation_space(self, agent: str) -> gym.spaces.Space:
        self._slot(agent)
        return self._observation_space

    def action_space(self, agent: str) -> gym.spaces.Space:
        self._slot(agent)
        return self._action_space

    def _outcomes(
        self,
        live: list[str],
        rows: Mapping[str, int],
        reward: np.ndarray,
        terminated: np.ndarray,
        truncated: np.ndarray,
        info: Callable[[int], dict[str, Any]],
    ) -> tuple[
        dict[str, float], dict[str, bool], dict[str, bool], dict[str, dict[str, Any]], list[str]
    ]:
        """A step's rewards, terminations, truncations and infos of the ``live`` cars (each at
        its row of the arrays; ``info(row)`` builds its info), and the cars whose episode
        ended: they leave the road, and ``agents`` keeps the others."""
        rewards = {agent: float(reward[rows[agent]]) for agent in live}
        terminations = {agent: bool(terminated[rows[agent]]) for agent in live}
        truncations = {agent: bool(truncated[rows[agent]]) for agent in live}
        infos = {agent: info(rows[agent]) for agent in live}
        ended = [agent for agent in live if terminations[agent] or truncations[agent]]
        self.agents = [agent for agent in live if agent not in ended]
        return rewards, terminations, truncations, infos, ended

    def _live_agents(self) -> list[str]:
        """The cars that act this step; none left means the episode is over for all."""
        if not self.agents:
            raise RuntimeError(
                "every car's episode has ended (agents is empty): call reset() first"
            )
        return list(self.agents)

    def _slot(self, agent: str) -> int:
        try:
            return self._index[agent]
        except KeyError:
            raise KeyError(
                f"no agent {agent!r} on this road; its agents are {self.possible_agents}"
            ) from None


def check_parallel_actions(actions: Any, live: list[str], possible: list[str]) -> list[int]:
    """One action in [0, ACTION_COUNT) for each of the ``live`` agents, in their order.

    Missing live agents, agents that are not live (finished, or unknown) and actions that are
    not integers in range are refused, naming the agents."""
    if not hasattr(actions, "keys"):
        raise ValueError(
            f"expected a dict of actions keyed by agent (live: {live}), "
            f"got {type(actions).__name__}"
        )
    unknown = sorted(set(actions) - set(live), key=str)
    missing = [a for a in live if a not in actions]
    if unknown or missing:
        problems = []
        if missing:
            problems.append(f"missing {missing}")
        if unknown:
            finished = [a for a in unknown if a in possible]
            problems.append(
                f"got actions for {unknown}"
                + (f" (finished this episode: {finished})" if finished else "")
            )
        raise ValueError(f"expected one action for each live agent {live}; " + "; ".join(problems))
    chosen = []
    for agent in live:
        value = actions[agent]
        if not _is_integer(value):
            raise ValueError(
                f"action of {agent!r} must be an integer in [0, {ACTION_COUNT}) "
                f"({', '.join(ACTION_NAMES)}), got {value!r}"
            )
        if not 0 <= int(value) < ACTION_COUNT:
            raise ValueError(
                f"action of {agent!r} must be in [0, {ACTION_COUNT}) "
                f"({', '.join(ACTION_NAMES)}), got {int(value)}"
            )
        chosen.append(int(value))
    return chosen


def _is_integer(value: Any) -> bool:
    """An int, a numpy integer or a 0-d integer array (what action spaces sample); not a bool."""
    if isinstance(value, (bool, np.bool_)):
        return False
    if isinstance(value, (int, np.integer)):
        return True
    return isinstance(value, np.ndarray) and value.shape == () and value.dtype.kind in "iu"
