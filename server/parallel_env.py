"""``HighwayParallelEnv``: several learning cars on one road, in PettingZoo's Parallel API.

One arena holds ``agents`` controlled cars (``car_0``, ``car_1``, ...) among the preset's
traffic; every live car acts in every step, as in PettingZoo's ``ParallelEnv``. Each car has
the single-agent spaces of ``overtake/Highway-v0`` (a Dict of the preset's sensors, five
actions) and its own reward, flags and info (``action_mask``, ``action_applied``,
``reward_terms``; ``metrics`` when its episode ends).

PettingZoo's rule for an agent whose episode ended (a crash terminates it, the time limit
truncates it) is that it leaves until the next ``reset``: here its car is taken off the road
(invisible to the sensors and to traffic, it can no longer collide), while the others drive on.
When the last car has left, ``agents`` is empty and the episode is over. This differs from the
server's shared roads, where a car that ended restarts behind the others at once (Gymnasium's
autoreset): those serve trainers that never stop, this serves PettingZoo's episodes.

With one agent it is ``HighwayEnv`` bit for bit (same seed, same actions).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from pettingzoo import ParallelEnv

from overtake.protocol.envs import (
    ParallelAgents,
    arena_seeds,
    check_parallel_actions,
    check_render_mode,
)
from overtake.protocol.vocabulary import DEFAULT_ACTION

from .env import _resolve_config, observation_space
from .sim import HighwaySim, SimConfig, autoreset_round
from .sim.render import render_top_down

AgentID = str


class HighwayParallelEnv(ParallelAgents, ParallelEnv[AgentID, dict[str, np.ndarray], int]):
    """``agents`` learning cars on one simulated road (Min et al. 2018 by default)."""

    # PettingZoo's convention: a class attribute, replaced per instance with its frame rate.
    metadata: dict[str, Any] = {  # noqa: RUF012
        "name": "overtake_highway_parallel_v0",
        "render_modes": ["rgb_array"],
        "render_fps": 10,
        "is_parallelizable": True,
    }

    def __init__(
        self,
        agents: int = 2,
        preset: str = "min2018",
        overrides: Mapping[str, Any] | None = None,
        config: SimConfig | None = None,
        render_mode: str | None = None,
    ) -> None:
        check_render_mode(render_mode, self.metadata["render_modes"])
        self.config = _resolve_config(preset, overrides, config)
        self.render_mode = render_mode
        self.sim = HighwaySim(self.config, num_arenas=1, agents_per_arena=agents)
        self._init_agents(agents, observation_space(self.sim))
        self._on_road = np.zeros(agents, dtype=bool)
        self.decision_period_s = self.config.episode.decision_period_s
        self.max_episode_steps = self.config.episode.max_decisions
        self.metadata = {**self.metadata, "render_fps": 1.0 / self.decision_period_s}

    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[AgentID, dict[str, np.ndarray]], dict[AgentID, dict[str, Any]]]:
        """Start a new episode for every car; ``seed`` re-creates the road's generator (None
        continues its stream). ``options`` is accepted and unused."""
        self.sim.reset(seeds=arena_seeds(seed, 1))
        self._on_road[:] = True
        self.agents = list(self.possible_agents)
        observations = self._observations(self.agents)
        mask = self.sim.action_mask()[0]
        infos = {
            agent: {
                "action_mask": mask[i],
                "action_applied": -1,
                "reward_terms": {name: 0.0 for name in self.sim.reward_terms},
            }
            for i, agent in enumerate(self.agents)
        }
        return observations, infos

    def step(
        self, actions: Mapping[AgentID, Any]
    ) -> tuple[
        dict[AgentID, dict[str, np.ndarray]],
        dict[AgentID, float],
        dict[AgentID, bool],
        dict[AgentID, bool],
        dict[AgentID, dict[str, Any]],
    ]:
        """Every live car acts at once; a car whose episode ends leaves the road."""
        live = self._live_agents()
        chosen = np.full((1, len(self.possible_agents)), DEFAULT_ACTION, dtype=np.int64)
        picked = check_parallel_actions(actions, live, self.possible_agents)
        chosen[0, [self._index[a] for a in live]] = picked
        result = autoreset_round(
            self.sim,
            chosen,
            np.zeros_like(chosen, dtype=bool),
            self._on_road[None].copy(),
        )
        mask = self.sim.action_mask()[0]
        metrics = self.sim.metrics() if result.ended.any() else None

        def info(i: int) -> dict[str, Any]:
            out: dict[str, Any] = {
                "action_mask": mask[i],
                "action_applied": int(result.action_applied[0, i]),
                "reward_terms": {n: float(v[0, i]) for n, v in result.reward_terms.items()},
            }
            if result.ended[0, i] and metrics is not None:
                out["metrics"] = {name: float(v[0, i]) for name, v in metrics.items()}
            return out

        rewards, terminations, truncations, infos, ended = self._outcomes(
            live, self._index, result.reward[0], result.terminated[0], result.truncated[0], info
        )
        # Observations before the finished cars leave: their last view of the road.
        observations = self._observations(live)
        gone = [self._index[a] for a in ended]
        if gone:
            self.sim.remove_agents(0, gone)
            self._on_road[gone] = False
        return observations, rewards, terminations, truncations, infos

    def _observations(self, agents: list[AgentID]) -> dict[AgentID, dict[str, np.ndarray]]:
        batch = self.sim.observe()
        return {
            agent: {key: value[0, self._index[agent]] for key, value in batch.items()}
            for agent in agents
        }

    def render(self) -> np.ndarray | None:
        if self.render_mode == "rgb_array":
            return render_top_down(self.sim)
        return None

    def close(self) -> None:
        """Nothing to release (the road lives in this process)."""
