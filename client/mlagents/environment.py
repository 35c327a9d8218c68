"""``RemoteEnvironment``: the low-level API of ML-Agents' ``BaseEnv`` over an overtake server.

It follows ``mlagents_envs.base_env`` (mlagents-envs 1.1.0) closely enough that ML-Agents' own
wrappers drive it unchanged (``UnityToGymWrapper``, ``UnityParallelEnv``, ``UnityAECEnv``; see
:mod:`overtake.client.mlagents.wrappers` and tests/client/test_mlagents.py, which run them), without
depending on mlagents-envs: ``behavior_specs``, ``get_steps``, ``set_actions``,
``set_action_for_agent``, ``step``, ``reset``, ``close``; ``DecisionSteps`` /
``TerminalSteps`` (indexing by agent id, ``agent_id_to_index``, ``group_id``,
``group_reward``, ``empty``), ``BehaviorSpec``,
``ObservationSpec`` (``dimension_property``, ``observation_type``), ``ActionSpec``
(``is_discrete``, ``is_continuous``, ...) and ``ActionTuple``. One environment holds one group
of arenas (one behaviour); agent ids are ids within the group, and several agents per arena
share a road.

Observations come as mlagents-envs 1.1.0 delivers Unity's: float32, camera pixels scaled to
[0, 1], images channels-first (the grey camera, the LIDAR map, Ho's grid: (1, height, width);
the RGB camera: (3, height, width)). The raw observations (uint8 pixels, the reward terms, the
metrics) are in :attr:`RemoteEnvironment.steps`.

As in ML-Agents, an agent whose episode ended is in ``TerminalSteps`` (``interrupted`` when it
hit the time limit), and after the next :meth:`RemoteEnvironment.step` it is back in
``DecisionSteps`` with the first observation of its new episode. Action masks follow ML-Agents:
``True`` marks an action that can NOT be taken. What overtake has not got (continuous actions,
side channels) is refused with :class:`UnsupportedRequest`, which says what is supported.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from overtake.client.mlagents.types import (
    ActionSpec,
    ActionTuple,
    BehaviorSpec,
    DecisionStep,
    DecisionSteps,
    DimensionProperty,
    ObservationSpec,
    ObservationType,
    TerminalStep,
    TerminalSteps,
    UnsupportedRequest,
    behavior_spec,
    mlagents_observation_spec,
    mlagents_observations,
)
from overtake.client.wire.connection import Connection
from overtake.client.wire.remote import ArenaGroup
from overtake.client.wire.remote_config import RemoteConfig
from overtake.envs.registry import arena_seeds
from overtake.ipc.transport import Endpoints
from overtake.protocol.messages import (
    JoinRequest,
    OpenRequest,
    Scalar,
    Steps,
)
from overtake.protocol.vocabulary import ACTION_COUNT, DEFAULT_ACTION, DEFAULT_PRESET

__all__ = [
    "ActionSpec",
    "ActionTuple",
    "BehaviorSpec",
    "DecisionStep",
    "DecisionSteps",
    "DimensionProperty",
    "ObservationSpec",
    "ObservationType",
    "RemoteEnvironment",
    "TerminalStep",
    "TerminalSteps",
    "UnsupportedRequest",
    "behavior_spec",
    "mlagents_observation_spec",
    "mlagents_observations",
]


class _NoSideChannels:
    """Stands where a ``UnityEnvironment`` keeps its side-channel manager: ML-Agents'
    PettingZoo wrappers read ``env._side_channel_manager._side_channels_dict`` to list the
    channels. overtake has none (simulator settings are ``overrides`` at open)."""

    _side_channels_dict: dict[Any, Any] = {}  # noqa: RUF012 - never written


class RemoteEnvironment:
    """Arenas on a remote simulator server, driven the way ML-Agents drives a Unity scene.

    ``connect``: the server's (or a router's) Zenoh endpoint. ``arenas`` × ``agents_per_arena``
    cars are opened with ``preset`` and ``overrides``; this trainer drives ``claim`` of each
    arena's cars (all by default) and others may join the rest. ``join``: instead of opening,
    join that arena id of ``config.server`` with one car.
    """

    def __init__(
        self,
        connect: Endpoints | None = None,
        *,
        preset: str = DEFAULT_PRESET,
        overrides: Mapping[str, Scalar] | None = None,
        arenas: int = 1,
        agents_per_arena: int = 1,
        claim: int | None = None,
        seed: int | None = None,
        join: int | None = None,
        config: RemoteConfig | None = None,
        side_channels: Sequence[Any] | None = None,
    ) -> None:
        if side_channels:
            raise UnsupportedRequest(
                "overtake has no side channels; got "
                f"{[type(c).__name__ for c in side_channels]}. Simulator settings are "
                "overrides given at open (overrides={'traffic.density': 'heavy'}), the seed "
                "is reset(seed=...)"
            )
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
        self._spec = behavior_spec(spec)
        self._side_channel_manager = _NoSideChannels()
        self._actions: dict[int, int] = {}
        self._steps: Steps = self.group.last  # type: ignore[assignment]
        self._closed = False

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
        if self._closed:
            raise RuntimeError(f"the environment of behaviour {behavior_name!r} is closed")

    def get_steps(self, behavior_name: str) -> tuple[DecisionSteps, TerminalSteps]:
        self._check_name(behavior_name)
        s = self._steps
        ended = s.ended
        deciding = ~ended
        group = np.zeros(len(s.agents), dtype=np.int32)
        decision = DecisionSteps(
            obs=[mlagents_observations(s.observations[name][deciding]) for name in self._obs_names],
            reward=s.reward[deciding].astype(np.float32),
            agent_id=s.agents[deciding],
            action_mask=[s.action_mask[deciding] == 0],
            group_id=group[deciding],
            group_reward=np.zeros(int(deciding.sum()), dtype=np.float32),
        )
        terminal = TerminalSteps(
            obs=[mlagents_observations(s.observations[name][ended]) for name in self._obs_names],
            reward=s.reward[ended].astype(np.float32),
            interrupted=s.truncated[ended],
            agent_id=s.agents[ended],
            group_id=group[ended],
            group_reward=np.zeros(int(ended.sum()), dtype=np.float32),
        )
        return decision, terminal

    def set_actions(self, behavior_name: str, action: Any) -> None:
        """Actions for every agent in the current DecisionSteps, in their order: an
        ActionTuple (overtake's or ML-Agents' own) with ``discrete`` of shape (agents, 1), or
        a plain array of (agents,) or (agents, 1)."""
        self._check_name(behavior_name)
        deciding = self._steps.agents[~self._steps.ended]
        values = np.asarray(_discrete_part(action))
        if values.ndim == 2 and values.shape[1] == 1:
            values = values[:, 0]
        if values.shape != (len(deciding),):
            raise ValueError(
                f"expected {len(deciding)} discrete action(s) (one per agent in "
                f"DecisionSteps, shape ({len(deciding)}, 1)), got shape "
                f"{np.shape(_discrete_part(action))}"
            )
        actions = {}
        for agent, value in zip(deciding, values):
            actions[int(agent)] = _checked_action(value)
        self._actions = actions

    def set_action_for_agent(self, behavior_name: str, agent_id: int, action: Any) -> None:
        """The action of one agent in the current DecisionSteps: an ActionTuple of one row, or
        a number."""
        self._check_name(behavior_name)
        values = np.asarray(_discrete_part(action)).reshape(-1)
        if values.size != 1:
            raise ValueError(
                f"expected one discrete action for agent {agent_id} (an ActionTuple of shape "
                f"(1, 1) or a number), got shape {np.shape(_discrete_part(action))}"
            )
        value = _checked_action(values[0])
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
        """Free the arenas and leave the network; again is a no-op (ML-Agents' PettingZoo
        wrappers close on garbage collection and at exit as well)."""
        if self._closed:
            return
        self._closed = True
        try:
            self.group.close()
        finally:
            self._connection.close()

    def __enter__(self) -> RemoteEnvironment:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _discrete_part(action: Any) -> Any:
    """The discrete actions of an ActionTuple (any class with ``continuous`` and ``discrete``,
    ML-Agents' included) or of a plain array; continuous actions are refused."""
    if not hasattr(action, "discrete"):
        return action
    continuous = getattr(action, "continuous", None)
    if continuous is not None and np.size(continuous) > 0:
        raise UnsupportedRequest(
            f"overtake's actions are discrete only (one branch of {ACTION_COUNT}: keep, "
            f"accelerate, decelerate, left, right); got continuous actions of shape "
            f"{np.shape(continuous)}"
        )
    if action.discrete is None:
        raise ValueError("the ActionTuple holds no discrete actions")
    return action.discrete


def _checked_action(value: Any) -> int:
    if not 0 <= int(value) < ACTION_COUNT:
        raise ValueError(f"action must be in [0, {ACTION_COUNT}), got {int(value)}")
    return int(value)


def _register_with_ml_agents() -> None:
    """Make ML-Agents' own ``isinstance`` checks see overtake's steps as theirs.

    ``UnityToGymWrapper`` tells an ended episode by ``isinstance(steps, TerminalSteps)`` with
    ML-Agents' class, which a look-alike fails. ML-Agents' step classes are
    ``collections.abc.Mapping`` ABCs and ``BaseEnv`` an ABC, so where mlagents-envs is
    installed ours are registered as their virtual subclasses (no ML-Agents code changes, no
    dependency where it is absent; importing its ``base_env`` costs about 2 ms).
    """
    try:
        from mlagents_envs import base_env
    except ImportError:
        return
    base_env.DecisionSteps.register(DecisionSteps)
    base_env.TerminalSteps.register(TerminalSteps)
    base_env.BaseEnv.register(RemoteEnvironment)


_register_with_ml_agents()
