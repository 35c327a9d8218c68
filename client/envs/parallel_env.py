"""``RemoteHighwayParallelEnv``: several learning cars on one road of a remote simulator, in
PettingZoo's Parallel API.

The remote twin of :class:`overtake.server.parallel_env.HighwayParallelEnv`, and the same bit
for bit for the same preset, seed and actions: one arena of ``agents`` cars (``car_0``,
``car_1``, ...) opened on a server, every live car acting in every step (one message each
way). A car whose episode ended leaves the road until the next ``reset`` (PettingZoo's rule):
with the next step the client asks the server to retire it (protocol 1.3), so that the server
does not restart it behind the others as it does on shared roads. A server older than 1.3 would
ignore that and is refused when the environment opens.

A server restart ends the episode: every live car is truncated (``info["server_restarted"]``),
and ``reset`` starts the next one on whichever server reopened the arena.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from pettingzoo import ParallelEnv

from overtake.client.envs.remote_gym import _Remote, _RemoteHandles, spaces_from_spec
from overtake.client.wire.connection import RemoteConfig
from overtake.protocol.envs import ParallelAgents, check_parallel_actions, check_render_mode
from overtake.protocol.messages import Scalar, Steps

AgentID = str
RETIRE_SINCE_MINOR = 3  # the protocol minor version that lets a trainer retire its cars


class RemoteHighwayParallelEnv(
    _RemoteHandles, ParallelAgents, ParallelEnv[AgentID, dict[str, np.ndarray], int]
):
    """``agents`` learning cars on one road of a remote simulator server."""

    metadata: dict[str, Any] = {  # noqa: RUF012
        "name": "overtake_remote_highway_parallel_v0",
        "render_modes": [],
        "render_fps": 10,
        "is_parallelizable": True,
    }

    def __init__(
        self,
        agents: int = 2,
        connect: str | Sequence[str] | None = None,
        preset: str = "min2018",
        overrides: Mapping[str, Scalar] | None = None,
        remote: RemoteConfig | None = None,
        render_mode: str | None = None,
    ) -> None:
        check_render_mode(render_mode, self.metadata["render_modes"])
        # A car whose episode ended must leave the road (Actions.retire, protocol 1.3).
        retire = (RETIRE_SINCE_MINOR, "several cars on one road in PettingZoo's API")
        self._remote = _Remote(
            connect,
            remote,
            preset,
            overrides,
            arenas=1,
            seed=None,
            agents_per_arena=agents,
            needs=(retire,),
        )
        spec = self._remote.spec
        self._init_agents(agents, spaces_from_spec(spec))
        self._retire_next: list[int] = []
        self.decision_period_s = spec.decision_period_s
        self.max_episode_steps = spec.max_episode_steps
        self.metadata = {**self.metadata, "render_fps": 1.0 / self.decision_period_s}

    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[AgentID, dict[str, np.ndarray]], dict[AgentID, dict[str, Any]]]:
        """Start a new episode for every car; ``seed`` re-creates the road's generator (None
        continues its stream). ``options`` is accepted and unused."""
        steps = self.group.reset((0,), (seed,))
        self._retire_next = []
        self.agents = list(self.possible_agents)
        rows = self._rows(steps)
        observations = self._observations(steps, rows, self.agents)
        infos = {agent: self._info(steps, rows[agent]) for agent in self.agents}
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
        chosen = check_parallel_actions(actions, live, self.possible_agents)
        restarts = self.group.restarts
        steps = self.group.step(
            np.array([self._index[a] for a in live], dtype=np.int32),
            np.array(chosen, dtype=np.int64),
            retire=self._retire_next,
        )
        restarted = self.group.restarts != restarts
        rows = self._rows(steps)

        def info(row: int) -> dict[str, Any]:
            out = self._info(steps, row)
            if restarted:
                out["server_restarted"] = True
            return out

        # A server restart ends the episode for every car (the road is gone).
        truncated = steps.truncated | restarted
        rewards, terminations, truncations, infos, ended = self._outcomes(
            live, rows, steps.reward, steps.terminated, truncated, info
        )
        observations = self._observations(steps, rows, live)
        self._retire_next = [self._index[a] for a in ended]
        return observations, rewards, terminations, truncations, infos

    def _rows(self, steps: Steps) -> dict[AgentID, int]:
        """Each agent's row in the server's Steps (agent ids are slots of the one arena)."""
        return {self.possible_agents[int(agent)]: row for row, agent in enumerate(steps.agents)}

    @staticmethod
    def _observations(
        steps: Steps, rows: dict[AgentID, int], agents: list[AgentID]
    ) -> dict[AgentID, dict[str, np.ndarray]]:
        return {
            agent: {name: value[rows[agent]] for name, value in steps.observations.items()}
            for agent in agents
        }

    def _info(self, steps: Steps, row: int) -> dict[str, Any]:
        info: dict[str, Any] = {
            "action_mask": steps.action_mask[row],
            "action_applied": int(steps.action_applied[row]),
            "reward_terms": {
                name: float(steps.reward_terms[row, i])
                for i, name in enumerate(self._remote.reward_terms)
            },
        }
        if steps.terminated[row] or steps.truncated[row]:
            info["metrics"] = {
                name: float(steps.metrics[row, i])
                for i, name in enumerate(self._remote.metric_fields)
            }
        if steps.late[row]:
            info["late"] = True
        return info

    def render(self) -> None:
        """The remote road is watched with a spectator (overtake-spectate), not rendered."""
        return None

    def close(self) -> None:
        """Free the arena on the server and leave the network."""
        self._remote.close()
