"""PettingZoo's Parallel API over an engine: several learning cars on one road.

One arena holds ``agents`` controlled cars (``car_0``, ``car_1``, ...) among the preset's
traffic; every live car acts in every step (one round of the engine). Each car has the
single-agent spaces (a Dict of the preset's sensors, five actions) and its own reward, flags
and info (:class:`~overtake.envs.faces.StepInfo`, as the single environment's).

PettingZoo's rule for an agent whose episode ended (a crash terminates it, the time limit
truncates it) is that it leaves until the next ``reset``: with the next step the face asks the
engine to retire its car (protocol 1.3), which takes it off the road (invisible to the sensors
and to traffic, it can no longer collide) instead of restarting it behind the others, as the
server's shared roads do for trainers that never stop. When the last car has left, ``agents``
is empty and the episode is over. A server restart ends the episode: every live car is
truncated (``info["server_restarted"]``).

Imports PettingZoo, an optional dependency (``pip install overtake[pettingzoo]``).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import gymnasium as gym
import numpy as np

try:
    from pettingzoo import ParallelEnv
except ModuleNotFoundError as error:
    if error.name != "pettingzoo":
        raise
    raise ModuleNotFoundError(
        "overtake's PettingZoo environments need PettingZoo, an optional dependency: "
        'pip install -e ".[pettingzoo]" (from the checkout; scripts/setup.sh pettingzoo) '
        "installs it",
        name="pettingzoo",
    ) from None

from overtake.protocol.vocabulary import ACTION_COUNT, ACTION_NAMES

from .faces import Faced, Simulator, spaces_from_spec
from .registry import check_render_mode
from .step_rows import StepInfo, StepRows

AgentID = str
RETIRE_SINCE_MINOR = 3  # the protocol minor version that lets a trainer retire its cars


def agent_names(count: int) -> list[str]:
    """The PettingZoo agent names of a road with ``count`` learning cars: car_0, car_1, ..."""
    return [f"car_{i}" for i in range(count)]


class ParallelFace(Faced, ParallelEnv[AgentID, dict[str, np.ndarray], int]):
    """``agents`` learning cars on one road of a simulator of one engine."""

    # PettingZoo's convention: a class attribute, replaced per instance (the render modes and
    # frame rate are the simulator's).
    metadata: dict[str, Any] = {  # noqa: RUF012
        "name": "overtake_highway_parallel_v0",
        "render_modes": ["rgb_array"],
        "render_fps": 10,
        "is_parallelizable": True,
    }

    def __init__(self, simulator: Simulator, render_mode: str | None = None) -> None:
        self.simulator = simulator
        spec = simulator.spec
        self.metadata = {
            **self.metadata,
            "render_modes": self._render_modes(),
            "render_fps": 1.0 / spec.decision_period_s,
        }
        check_render_mode(render_mode, self.metadata["render_modes"])
        self.render_mode = render_mode
        (self._engine,) = simulator.parts
        count = spec.agents_per_arena
        self.possible_agents = agent_names(count)
        self.agents: list[AgentID] = []
        self._index = {name: i for i, name in enumerate(self.possible_agents)}
        # One space object for every agent: PettingZoo's API test checks that an agent gets
        # the same object every time.
        self._observation_space = spaces_from_spec(spec)
        self._action_space: gym.spaces.Discrete = gym.spaces.Discrete(ACTION_COUNT)
        self._retire_next: list[int] = []
        self.decision_period_s = spec.decision_period_s
        self.max_episode_steps = spec.max_episode_steps

    def observation_space(self, agent: AgentID) -> gym.spaces.Space:
        self._slot(agent)
        return self._observation_space

    def action_space(self, agent: AgentID) -> gym.spaces.Space:
        self._slot(agent)
        return self._action_space

    def reset(
        self, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[dict[AgentID, dict[str, np.ndarray]], dict[AgentID, dict[str, Any]]]:
        """Start a new episode for every car; ``seed`` re-creates the road's generator (None
        continues its stream). ``options`` is accepted and unused."""
        steps = self._engine.reset((0,), (seed,))
        self._retire_next = []
        self.agents = list(self.possible_agents)
        rows = self._rows(steps)
        info = StepInfo.of(steps, self.simulator.spec)
        return (
            self._observations(steps, rows, self.agents),
            {agent: info.agent(rows[agent]) for agent in self.agents},
        )

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
        if not self.agents:
            raise RuntimeError(
                "every car's episode has ended (agents is empty): call reset() first"
            )
        live = list(self.agents)
        chosen = check_parallel_actions(actions, live, self.possible_agents)
        engine = self._engine
        restarts = engine.restarts
        engine.send(
            np.array([self._index[a] for a in live], dtype=np.int32),
            np.array(chosen, dtype=np.int64),
            retire=self._retire_next,
        )
        steps = engine.receive()
        restarted = engine.restarts != restarts
        rows = self._rows(steps)
        info = StepInfo.of(steps, self.simulator.spec, restarted=restarted)
        # A server restart ends the episode for every car (the road is gone).
        truncated = steps.truncated | restarted
        rewards = {agent: float(steps.reward[rows[agent]]) for agent in live}
        terminations = {agent: bool(steps.terminated[rows[agent]]) for agent in live}
        truncations = {agent: bool(truncated[rows[agent]]) for agent in live}
        infos = {agent: info.agent(rows[agent]) for agent in live}
        ended = [agent for agent in live if terminations[agent] or truncations[agent]]
        self.agents = [agent for agent in live if agent not in ended]
        self._retire_next = [self._index[a] for a in ended]
        # Their last view of the road, the finished cars' included.
        return self._observations(steps, rows, live), rewards, terminations, truncations, infos

    def _rows(self, steps: StepRows) -> dict[AgentID, int]:
        """Each agent's row in the Steps (agent ids are slots of the one arena)."""
        return {self.possible_agents[int(agent)]: row for row, agent in enumerate(steps.agents)}

    @staticmethod
    def _observations(
        steps: StepRows, rows: dict[AgentID, int], agents: list[AgentID]
    ) -> dict[AgentID, dict[str, np.ndarray]]:
        return {
            agent: {name: value[rows[agent]] for name, value in steps.observations.items()}
            for agent in agents
        }

    def _slot(self, agent: AgentID) -> int:
        try:
            return self._index[agent]
        except KeyError:
            raise KeyError(
                f"no agent {agent!r} on this road; its agents are {self.possible_agents}"
            ) from None

    def render(self) -> np.ndarray | None:
        """The road from above (in process; a remote road is watched with a spectator)."""
        road = self.simulator.road
        if self.render_mode == "rgb_array" and road is not None:
            return road.picture(0)
        return None

    def close(self) -> None:
        """Free the arena (on a server: and leave the network)."""
        self.simulator.close()


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
