"""ML-Agents' low-level types (``mlagents_envs.base_env``, mlagents-envs 1.1.0) as overtake
builds them without depending on mlagents-envs: the observation, action and behaviour specs,
action tuples, and the decision and terminal steps of a batch of agents; and how overtake's
observations are laid out in them (as mlagents-envs delivers a Unity scene's: float32, pixels
scaled to [0, 1], images channels-first)."""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from enum import Enum, IntFlag
from typing import NamedTuple

import numpy as np

from overtake.protocol.messages import (
    BehaviourSpec as WireBehaviourSpec,
)


class UnsupportedRequest(ValueError):
    """A caller (an ML-Agents wrapper, a trainer) asked for something overtake does not offer:
    continuous actions, a side channel, an unknown behaviour. The message names what was asked
    and what is supported."""


class DimensionProperty(IntFlag):
    """What a dimension of an observation is (ML-Agents' ``DimensionProperty``, same values)."""

    UNSPECIFIED = 0
    NONE = 1
    TRANSLATIONAL_EQUIVARIANCE = 2
    VARIABLE_SIZE = 4


class ObservationType(Enum):
    """What an observation carries (ML-Agents' ``ObservationType``, same values)."""

    DEFAULT = 0
    GOAL_SIGNAL = 1


class ObservationSpec(NamedTuple):
    """One observation of an agent, as ML-Agents describes it: images are (channels, height,
    width) with two translationally equivariant dimensions, vectors (size,)."""

    shape: tuple[int, ...]
    dimension_property: tuple[DimensionProperty, ...]
    observation_type: ObservationType
    name: str


class ActionTuple:
    """Actions for several agents (ML-Agents' ``ActionTuple``): ``continuous`` is (agents,
    continuous size) float32 and ``discrete`` (agents, branches) int32; whichever is not given
    is an (agents, 0) array once the other is added."""

    def __init__(
        self, continuous: np.ndarray | None = None, discrete: np.ndarray | None = None
    ) -> None:
        self._continuous: np.ndarray | None = None
        self._discrete: np.ndarray | None = None
        if continuous is not None:
            self.add_continuous(continuous)
        if discrete is not None:
            self.add_discrete(discrete)

    @property
    def continuous(self) -> np.ndarray | None:
        return self._continuous

    @property
    def discrete(self) -> np.ndarray | None:
        return self._discrete

    @property
    def discrete_dtype(self) -> type[np.int32]:
        return np.int32

    def add_continuous(self, continuous: np.ndarray) -> None:
        continuous = np.asarray(continuous, dtype=np.float32)
        if self._discrete is None:
            self._discrete = np.zeros((continuous.shape[0], 0), dtype=np.int32)
        self._continuous = continuous

    def add_discrete(self, discrete: np.ndarray) -> None:
        discrete = np.asarray(discrete, dtype=np.int32)
        if self._continuous is None:
            self._continuous = np.zeros((discrete.shape[0], 0), dtype=np.float32)
        self._discrete = discrete


class ActionSpec(NamedTuple):
    """The actions of a behaviour (ML-Agents' ``ActionSpec``); overtake's are one discrete
    branch of :data:`~overtake.protocol.vocabulary.ACTION_COUNT` actions."""

    continuous_size: int
    discrete_branches: tuple[int, ...]

    def __str__(self) -> str:
        return f"Continuous: {self.continuous_size}, Discrete: {self.discrete_branches}"

    def is_discrete(self) -> bool:
        return self.discrete_size > 0 and self.continuous_size == 0

    def is_continuous(self) -> bool:
        return self.discrete_size == 0 and self.continuous_size > 0

    @property
    def discrete_size(self) -> int:
        return len(self.discrete_branches)

    def empty_action(self, n_agents: int) -> ActionTuple:
        return ActionTuple(
            continuous=np.zeros((n_agents, self.continuous_size), dtype=np.float32),
            discrete=np.zeros((n_agents, self.discrete_size), dtype=np.int32),
        )

    def random_action(self, n_agents: int) -> ActionTuple:
        rng = np.random.default_rng()
        discrete = np.zeros((n_agents, self.discrete_size), dtype=np.int32)
        for branch, size in enumerate(self.discrete_branches):
            discrete[:, branch] = rng.integers(0, size, size=n_agents)
        return ActionTuple(
            continuous=rng.uniform(-1.0, 1.0, size=(n_agents, self.continuous_size)),
            discrete=discrete,
        )

    @staticmethod
    def create_discrete(discrete_branches: tuple[int, ...]) -> ActionSpec:
        return ActionSpec(0, tuple(discrete_branches))

    # ML-Agents' other constructors, for code that builds specs; no overtake behaviour has
    # continuous actions, and RemoteEnvironment refuses them.
    @staticmethod
    def create_continuous(continuous_size: int) -> ActionSpec:
        return ActionSpec(continuous_size, ())

    @staticmethod
    def create_hybrid(continuous_size: int, discrete_branches: tuple[int, ...]) -> ActionSpec:
        return ActionSpec(continuous_size, tuple(discrete_branches))


class BehaviorSpec(NamedTuple):
    observation_specs: list[ObservationSpec]
    action_spec: ActionSpec


def mlagents_observation_spec(name: str, shape: tuple[int, ...]) -> ObservationSpec:
    """The ML-Agents spec of one of overtake's observations: an image (the grey camera, the
    LIDAR map, Ho's grid: (height, width); the RGB camera: (height, width, 3)) becomes
    channels-first (1 or 3, height, width) with dimension properties NONE, TE, TE, as
    mlagents-envs 1.1.0 delivers a Unity camera's (its PNG decoding moves channels first) and
    as mlagents-learn's visual encoders read it; a vector stays (size,)."""
    prop: tuple[DimensionProperty, ...]
    if len(shape) in (2, 3):
        height, width = shape[:2]
        channels = 1 if len(shape) == 2 else shape[2]
        shape = (channels, height, width)
        prop = (
            DimensionProperty.NONE,
            DimensionProperty.TRANSLATIONAL_EQUIVARIANCE,
            DimensionProperty.TRANSLATIONAL_EQUIVARIANCE,
        )
    else:
        prop = (DimensionProperty.NONE,) * len(shape)
    return ObservationSpec(
        shape=tuple(shape),
        dimension_property=prop,
        observation_type=ObservationType.DEFAULT,
        name=name,
    )


def mlagents_observations(batch: np.ndarray) -> np.ndarray:
    """(agents, ...) of one observation as ML-Agents hands it to trainers: float32, pixels
    (uint8) scaled to [0, 1] as Unity's cameras are, images channels-first (see
    :func:`mlagents_observation_spec`)."""
    if batch.dtype == np.uint8:
        out = batch.astype(np.float32) / np.float32(255.0)
    else:
        out = batch.astype(np.float32, copy=False)
    if out.ndim == 3:
        return out[:, None]
    if out.ndim == 4:
        return np.moveaxis(out, 3, 1)
    return out


def behavior_spec(spec: WireBehaviourSpec) -> BehaviorSpec:
    """ML-Agents' BehaviorSpec of a behaviour the server described."""
    return BehaviorSpec(
        observation_specs=[mlagents_observation_spec(o.name, o.shape) for o in spec.observations],
        action_spec=ActionSpec.create_discrete(spec.action_branches),
    )


@dataclass(frozen=True)
class DecisionStep:
    obs: list[np.ndarray]
    reward: float
    agent_id: int
    action_mask: list[np.ndarray] | None
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

    def _row(self, agent_id: int) -> int:
        try:
            return self._index[int(agent_id)]
        except KeyError:
            raise KeyError(
                f"agent_id {agent_id} is not present in {type(self).__name__}; "
                f"present: {sorted(self._index)}"
            ) from None

    def __len__(self) -> int:
        return len(self.agent_id)

    def __iter__(self) -> Iterator[int]:
        yield from (int(a) for a in self.agent_id)


def _empty_obs(spec: BehaviorSpec) -> list[np.ndarray]:
    return [np.zeros((0, *o.shape), dtype=np.float32) for o in spec.observation_specs]


class DecisionSteps(_AgentSteps):
    """Agents that need an action: ``obs`` is one (agents, ...) array per observation spec;
    ``action_mask`` one (agents, branch size) bool array per branch, True where the action can
    NOT be taken (ML-Agents' convention)."""

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
        i = self._row(agent_id)
        return DecisionStep(
            obs=[o[i] for o in self.obs],
            reward=float(self.reward[i]),
            agent_id=int(agent_id),
            action_mask=None if self.action_mask is None else [m[i] for m in self.action_mask],
            group_id=int(self.group_id[i]),
            group_reward=float(self.group_reward[i]),
        )

    @staticmethod
    def empty(spec: BehaviorSpec) -> DecisionSteps:
        return DecisionSteps(
            obs=_empty_obs(spec),
            reward=np.zeros(0, dtype=np.float32),
            agent_id=np.zeros(0, dtype=np.int32),
            action_mask=None,
            group_id=np.zeros(0, dtype=np.int32),
            group_reward=np.zeros(0, dtype=np.float32),
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
        i = self._row(agent_id)
        return TerminalStep(
            obs=[o[i] for o in self.obs],
            reward=float(self.reward[i]),
            interrupted=bool(self.interrupted[i]),
            agent_id=int(agent_id),
            group_id=int(self.group_id[i]),
            group_reward=float(self.group_reward[i]),
        )

    @staticmethod
    def empty(spec: BehaviorSpec) -> TerminalSteps:
        return TerminalSteps(
            obs=_empty_obs(spec),
            reward=np.zeros(0, dtype=np.float32),
            interrupted=np.zeros(0, dtype=bool),
            agent_id=np.zeros(0, dtype=np.int32),
            group_id=np.zeros(0, dtype=np.int32),
            group_reward=np.zeros(0, dtype=np.float32),
        )
