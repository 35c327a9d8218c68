"""``RemoteEnvironment``: the low-level API in the shape of ML-Agents' ``BaseEnv``.

It is duck-typed on ``mlagents_envs.base_env`` (``behavior_specs``, ``get_steps``,
``set_actions``, ``set_action_for_agent``, ``step``, ``reset``, ``close``; ``DecisionSteps``,
``TerminalSteps``, ``BehaviorSpec``, ``ActionTuple``) closely enough for ML-Agents' own
wrappers to drive it, without depending on mlagents-envs. One environment holds one group of
arenas (one behaviour); agent ids are ids within the group.

As in ML-Agents, an agent whose episode ended is in ``TerminalSteps`` (``interrupted`` when it
hit the time limit), and after the next :meth:`RemoteEnvironment.step` it is back in
``DecisionSteps`` with the first observation of its new episode. Action masks follow ML-Agents:
``True`` marks an action that can NOT be taken.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from overtake.protocol.envs import arena_seeds
from overtake.protocol.messages import JoinRequest, OpenRequest, Scalar, Steps
from overtake.protocol.vocabulary import ACTION_COUNT, DEFAULT_ACTION

from .remote import ArenaGroup, Connection, RemoteConfig


class ObservationSpec(NamedTuple):
    shape: tuple[int, ...]
    dimension_property: tuple[int, ...]
    observation_type: int
    name: str


class ActionSpec(NamedTuple):
    continuous_size: int
    discrete_branches: tuple[int, ...]

    @property
    def discrete_size(self) -> int:
        return len(self.discrete_branches)

    def empty_action(self, n_agents: int) -> ActionTuple:
        return ActionTuple(discrete=np.zeros((n_agents, self.discrete_size), dtype=np.int32))

    def random_action(self, n_agents: int) -> ActionTuple:
        rng = np.random.default_rng()
        return ActionTuple(
            discrete=np.column_stack(
                [rng.integers(0, b, size=n_agents) for b in self.discrete_branches]
            ).astype(np.int32)
        )


class BehaviorSpec(NamedTuple):
    observation_specs: list[ObservationSpec]
    action_spec: ActionSpec


class ActionTuple:
    """Actions for several agents: ``discrete`` is (agents, branches) int32."""

    def __init__(
        self, continuous: np.ndarray | None = None, discrete: np.ndarray | None = None
    ) -> None:
        self.continuous = (
            np.zeros((0, 0), dtype=np.float32)
            if continuous is None
            else np.asarray(continuous, dtype=np.float32)
        )
        self.discrete = (
            np.zeros((0, 0), dtype=np.int32)
            if discrete is None
            else np.asarray(discrete, dtype=np.int32)
        )


@dataclass(frozen=True)
class DecisionStep:
    obs: list[np.ndarray]
    reward: float
    agent_id: int
    action_mask: list[np.ndarray]
    group_id: int
    group_reward: float


@dataclass(frozen=True)
class TerminalStep:
    obs: list[np.ndarray]
    reward: float
    interrupted: bool
    agent_id: int
    group_id: int
    group_reward: float


class _AgentSteps(Mapping):
    """Rows of agents, looked up by agent id (ML-Agents' DecisionSteps / TerminalSteps)."""

    agent_id: np.ndarray

    def _index_agents(self) -> None:
        self._index = {int(a): i for i, a in enumerate(self.agent_id)}

    @property
    def agent_id_to_index(self) -> dict[int, int]:
        return self._index

    def __len__(self) -> int:
        return len(self.agent_id)

    def __iter__(self) -> Iterator[int]:
        yield from (int(a) for a in self.agent_id)


class DecisionSteps(_AgentSteps):
    """Agents that need an action: ``obs`` is one (agents, ...) array per observation spec."""

    def __init__(
        self,
        obs: list[np.ndarray],
        reward: np.ndarray,
        agent_id: np.ndarray,
        action_mask: list[np.ndarray] | None,
        group_id: np.ndarray,
        group_reward: np.ndarray,
    ) -> None:
        self.obs, self.reward, self.agent_id = obs, reward, agent_id
        self.action_mask, self.group_id, self.group_reward = action_mask, group_id, group_reward
        self._index_agents()

    def __getitem__(self, agent_id: int) -> DecisionStep:
        i = self._index[int(agent_id)]
        return DecisionStep(
            obs=[o[i] for o in self.obs],
            reward=float(self.reward[i]),
            agent_id=int(agent_id),
            action_mask=[m[i] for m in self.action_mask or []],
            group_id=int(self.group_id[i]),
            group_reward=float(self.group_reward[i]),
        )


class TerminalSteps(_AgentSteps):
    """Agents whose episode ended; ``interrupted`` marks the time limit."""

    def __init__(
        self,
        obs: list[np.ndarray],
        reward: np.ndarray,
        interrupted: np.ndarray,
        agent_id: np.ndarray,
        group_id: np.ndarray,
        group_reward: np.ndarray,
    ) -> None:
        self.obs, self.reward, self.interrupted = obs, reward, interrupted
        self.agent_id, self.group_id, self.group_reward = agent_id, group_id, group_reward
        self._index_agents()

    def __getitem__(self, agent_id: int) -> TerminalStep:
        i = self._index[int(agent_id)]
        return TerminalStep(
            obs=[o[i] for o in self.obs],
            reward=float(self.reward[i]),
            interrupted=bool(self.interrupted[i]),
            agent_id=int(agent_id),
            group_id=int(self.group_id[i]),
            group_reward=float(self.group_reward[i]),
        )


class RemoteEnvironment:
    """Arenas on a remote simulator server, driven the way ML-Agents drives a Unity scene.

    ``connect``: the server's (or a router's) Zenoh endpoint. ``arenas`` × ``agents_per_arena``
    cars are opened with ``preset`` and ``overrides``; this trainer drives ``claim`` of each
    arena's cars (all by default) and others may join the rest. ``join``: instead of opening,
    join that arena id of ``config.server`` with one car.
    """

    def __init__(
        self,
        connect: str | tuple[str, ...] | None = None,
        *,
        preset: str = "min2018",
        overrides: Mapping[str, Scalar] | None = None,
        arenas: int = 1,
        agents_per_arena: int = 1,
        claim: int | None = None,
        seed: int | None = None,
        join: int | None = None,
        config: RemoteConfig | None = None,
    ) -> None:
        if config is None:
            config = RemoteConfig.from_connect(connect)
        elif connect is not None:
            raise ValueError("pass either connect or a RemoteConfig, not both")
        self._connection = Connection(config)
        try:
            trainer = self._connection.trainer
            request: OpenRequest | JoinRequest
            if join is not None:
                request = JoinRequest(trainer=trainer, arena=join, agents=1)
            else:
                request = OpenRequest(
                    trainer=trainer,
                    preset=preset,
                    overrides=dict(overrides or {}),
                    arenas=arenas,
                    agents_per_arena=agents_per_arena,
                    claim=agents_per_arena if claim is None else claim,
                    seed=seed,
                )
            self.group = ArenaGroup.open(self._connection, request)
        except BaseException:
            self._connection.close()
            raise
        spec = self.group.spec
        assert spec is not None
        self.behavior_name = spec.name
        self._obs_names = [o.name for o in spec.observations]
        self._spec = BehaviorSpec(
            observation_specs=[
                ObservationSpec(
                    shape=o.shape, dimension_property=(), observation_type=0, name=o.name
                )
                for o in spec.observations
            ],
            action_spec=ActionSpec(continuous_size=0, discrete_branches=spec.action_branches),
        )
        self._actions: dict[int, int] = {}
        self._steps: Steps = self.group.last  # type: ignore[assignment]

    # --- BaseEnv ------------------------------------------------------------------------------

    @property
    def behavior_specs(self) -> Mapping[str, BehaviorSpec]:
        return {self.behavior_name: self._spec}

    @property
    def steps(self) -> Steps:
        """The latest raw :class:`~overtake.protocol.messages.Steps` (reward terms, metrics)."""
        return self._steps

    def _check_name(self, behavior_name: str) -> None:
        if behavior_name != self.behavior_name:
            raise KeyError(
                f"unknown behaviour {behavior_name!r}; this environment has {self.behavior_name!r}"
            )

    def get_steps(self, behavior_name: str) -> tuple[DecisionSteps, TerminalSteps]:
        self._check_name(behavior_name)
        s = self._steps
        ended = s.ended
        deciding = ~ended
        group = np.zeros(len(s.agents), dtype=np.int32)
        decision = DecisionSteps(
            obs=[s.observations[name][deciding] for name in self._obs_names],
            reward=s.reward[deciding].astype(np.float32),
            agent_id=s.agents[deciding],
            action_mask=[s.action_mask[deciding] == 0],
            group_id=group[deciding],
            group_reward=np.zeros(int(deciding.sum()), dtype=np.float32),
        )
        terminal = TerminalSteps(
            obs=[s.observations[name][ended] for name in self._obs_names],
            reward=s.reward[ended].astype(np.float32),
            interrupted=s.truncated[ended],
            agent_id=s.agents[ended],
            group_id=group[ended],
            group_reward=np.zeros(int(ended.sum()), dtype=np.float32),
        )
        return decision, terminal

    def set_actions(self, behavior_name: str, action: Any) -> None:
        """Actions for every agent in the current DecisionSteps, in their order."""
        self._check_name(behavior_name)
        decision, _ = self.get_steps(behavior_name)
        values = getattr(action, "discrete", action)
        values = np.asarray(values)
        if values.ndim == 2 and values.shape[1] == 1:
            values = values[:, 0]
        if values.shape != (len(decision),):
            raise ValueError(
                f"expected {len(decision)} discrete action(s) (one per agent in "
                f"DecisionSteps, shape ({len(decision)}, 1)), got shape "
                f"{np.shape(getattr(action, 'discrete', action))}"
            )
        self._actions = {}
        for agent, value in zip(decision.agent_id, values):
            self.set_action_for_agent(behavior_name, int(agent), int(value))

    def set_action_for_agent(self, behavior_name: str, agent_id: int, action: Any) -> None:
        self._check_name(behavior_name)
        value = getattr(action, "discrete", action)
        value = int(np.asarray(value).reshape(-1)[0])
        if not 0 <= value < ACTION_COUNT:
            raise ValueError(f"action must be in [0, {ACTION_COUNT}), got {value}")
        if agent_id not in set(int(a) for a in self._steps.agents[~self._steps.ended]):
            raise KeyError(
                f"agent {agent_id} is not in DecisionSteps; agents deciding now: "
                f"{self._steps.agents[~self._steps.ended].tolist()}"
            )
        self._actions[int(agent_id)] = value

    def step(self) -> None:
        """Send the set actions (keep for agents given none) and advance one decision."""
        agents = self._steps.agents
        actions = np.array(
            [self._actions.get(int(a), DEFAULT_ACTION) for a in agents], dtype=np.int64
        )
        self._steps = self.group.step(agents, actions)
        self._actions = {}

    def reset(self, seed: int | None = None) -> None:
        """New episodes in every arena (arena ``i`` seeded ``seed + i``)."""
        count = len(self.group.arena_ids)
        self._steps = self.group.reset(tuple(range(count)), tuple(arena_seeds(seed, count)))
        self._actions = {}

    def close(self) -> None:
        try:
            self.group.close()
        finally:
            self._connection.close()

    def __enter__(self) -> RemoteEnvironment:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
