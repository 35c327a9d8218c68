"""Gymnasium environments over a remote simulator: ``overtake/RemoteHighway-v0``.

The spaces are rebuilt from the server's behaviour spec, so they equal the in-process
environment's; observations, rewards, flags and info are the same too, bit for bit for the same
preset, seed and actions. The vector environment opens its N arenas as one group (one message
each way per step), or as ``parts`` groups stepped in turn (``send`` / ``recv``, for a trainer
that overlaps its work with the simulation), with Gymnasium 1.x next-step autoreset, as the
in-process vector env does.

A server restart is survived: the step that finds the server gone returns the last observation
with ``truncated`` set (``info["server_restarted"]``), the arenas are reopened (on the restarted
server or another one), and the next step (or reset) starts the new episodes.
"""

from __future__ import annotations

import dataclasses
import itertools
import json
from collections.abc import Mapping, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.vector.utils import batch_space

from overtake.client.wire.connection import Connection, RemoteConfig
from overtake.client.wire.remote import ArenaGroup
from overtake.protocol import errors
from overtake.protocol.codec import version_text
from overtake.protocol.envs import (
    ReportsEpisodeLength,
    arena_seeds,
    check_actions,
    check_render_mode,
)
from overtake.protocol.messages import (
    TYPED_SPEC_SINCE_MINOR,
    BehaviourSpec,
    OpenRequest,
    Scalar,
    Steps,
)
from overtake.protocol.vocabulary import ACTION_COUNT, EPISODE_COUNTS

try:  # Gymnasium >= 1.1 names the autoreset modes; 1.0 only has next-step autoreset.
    from gymnasium.vector import AutoresetMode

    _NEXT_STEP: Any = AutoresetMode.NEXT_STEP
except ImportError:  # pragma: no cover - Gymnasium 1.0
    _NEXT_STEP = "NextStep"


def _joined(parts: Sequence[Steps]) -> Steps:
    """One Steps of several groups' Steps, rows in the order given (server, group and round
    are the first part's: the rows are what the vector environment reads)."""
    if len(parts) == 1:
        return parts[0]
    first = parts[0]

    def rows(name: str) -> np.ndarray:
        return np.concatenate([getattr(p, name) for p in parts])

    return dataclasses.replace(
        first,
        agents=rows("agents"),
        observations={
            name: np.concatenate([p.observations[name] for p in parts])
            for name in first.observations
        },
        reward=rows("reward"),
        terminated=rows("terminated"),
        truncated=rows("truncated"),
        action_applied=rows("action_applied"),
        late=rows("late"),
        action_mask=rows("action_mask"),
        reward_terms=rows("reward_terms"),
        metrics=rows("metrics"),
    )


def spaces_from_spec(spec: BehaviourSpec) -> spaces.Dict:
    """The Dict observation space a behaviour spec describes."""
    return spaces.Dict(
        {
            o.name: spaces.Box(low=o.low, high=o.high, shape=o.shape, dtype=np.dtype(o.dtype).type)
            for o in spec.observations
        }
    )


# What a server's minor protocol version must be for these environments: (minor, what for).
TYPED_SPEC_NEED = (
    TYPED_SPEC_SINCE_MINOR,
    "this client reads the road, the car and the observations' columns and reach from the "
    "behaviour spec",
)


class _Remote:
    """The connection and the groups both Gymnasium environments are built on: one group, or
    ``parts`` groups of consecutive arenas (see :class:`RemoteHighwayVectorEnv`). ``needs``:
    (minor version, what for) the server must speak beyond :data:`TYPED_SPEC_NEED`; the
    oldest unmet one refuses it."""

    def __init__(
        self,
        connect: str | Sequence[str] | None,
        remote: RemoteConfig | None,
        preset: str,
        overrides: Mapping[str, Scalar] | None,
        arenas: int,
        seed: int | None,
        agents_per_arena: int = 1,
        parts: int = 1,
        needs: tuple[tuple[int, str], ...] = (),
    ) -> None:
        if not 1 <= parts <= arenas:
            raise ValueError(f"parts must be between 1 and the {arenas} arena(s), got {parts}")
        if remote is None:
            remote = RemoteConfig.from_connect(
                connect if connect is None or isinstance(connect, str) else tuple(connect)
            )
        elif connect is not None:
            raise ValueError("pass either connect or remote (a RemoteConfig), not both")
        self.connection = Connection(remote)
        self.groups: list[ArenaGroup] = []
        # Consecutive arenas per part, the first parts one larger where they do not divide.
        sizes = [len(a) for a in np.array_split(np.arange(arenas), parts)]
        try:
            for start, size in zip(np.cumsum([0, *sizes[:-1]]), sizes, strict=True):
                self.groups.append(
                    ArenaGroup.open(
                        self.connection,
                        OpenRequest(
                            trainer=self.connection.trainer,
                            preset=preset,
                            overrides=dict(overrides or {}),
                            arenas=size,
                            agents_per_arena=agents_per_arena,
                            claim=agents_per_arena,
                            seed=None if seed is None else seed + int(start),
                        ),
                    )
                )
        except BaseException:
            self.close()
            raise
        self.part_sizes = tuple(sizes)
        spec = self.group.spec
        assert spec is not None
        minor = self.group.server_minor
        for need, why in sorted((TYPED_SPEC_NEED, *needs)):
            if minor < need:
                self.close()
                raise errors.VersionMismatch(
                    f"server {self.group.server} speaks protocol 1.{minor}; {why}, which need "
                    f"1.{need} or newer (this client speaks {version_text()}): upgrade the "
                    "server"
                )
        self.spec = spec
        # A record of the server's configuration (run records keep it); nothing reads it.
        self.sim_config: dict[str, Any] = json.loads(spec.config_json)
        self.reward_terms = spec.reward_terms
        self.metric_fields = spec.metric_fields

    @property
    def group(self) -> ArenaGroup:
        """The first part's group (the only one without parts)."""
        return self.groups[0]

    def close(self) -> None:
        try:
            for group in self.groups:
                group.close()
        finally:
            self.connection.close()


class _RemoteHandles:
    """What both remote environments expose of their connection."""

    _remote: _Remote

    @property
    def group(self) -> ArenaGroup:
        """The arenas on the server (ids, server name, restarts survived); with ``parts``,
        the first part's (:attr:`groups` has them all)."""
        return self._remote.group

    @property
    def groups(self) -> tuple[ArenaGroup, ...]:
        """Every group of this environment's arenas, one per part, in the order of the
        environment indices."""
        return tuple(self._remote.groups)

    @property
    def trainer(self) -> str:
        """This trainer's name on the network (the servers' status lists it)."""
        return self._remote.connection.trainer

    @property
    def sim_config(self) -> dict[str, Any]:
        """The server's resolved configuration as plain nested data, a record: read
        :attr:`behaviour_spec` for what an agent sees and drives."""
        return self._remote.sim_config

    @property
    def behaviour_spec(self) -> BehaviourSpec:
        """What an agent sees and drives, as the server describes its arenas."""
        return self._remote.spec

    def label_step(self, step: int) -> None:
        """Send ``step`` (the trainer's count of environment steps, >= 0) with the following
        actions: the server repeats it in its world frames, so a spectator's recording of
        these arenas lies on the trainer's ``step`` timeline and opens beside its curves."""
        if step < 0:
            raise ValueError(f"a step count must be >= 0, got {step}")
        for group in self._remote.groups:
            group.trainer_step = int(step)


class RemoteHighwayEnv(_RemoteHandles, ReportsEpisodeLength, gym.Env):
    """One agent on one arena of a remote simulator server."""

    # Gymnasium's convention: a class attribute, replaced per instance with its frame rate.
    metadata = {"render_modes": [], "render_fps": 10}  # noqa: RUF012

    def __init__(
        self,
        connect: str | Sequence[str] | None = None,
        preset: str = "min2018",
        overrides: Mapping[str, Scalar] | None = None,
        remote: RemoteConfig | None = None,
        render_mode: str | None = None,
    ) -> None:
        check_render_mode(render_mode, self.metadata["render_modes"])
        self._remote = _Remote(connect, remote, preset, overrides, arenas=1, seed=None)
        spec = self._remote.spec
        self.observation_space = spaces_from_spec(spec)
        self.action_space = spaces.Discrete(ACTION_COUNT)
        self.decision_period_s = spec.decision_period_s
        self.max_episode_steps = spec.max_episode_steps
        self.metadata = {**self.metadata, "render_fps": 1.0 / self.decision_period_s}

    def _unpack(self, steps: Steps) -> tuple[dict[str, np.ndarray], dict[str, Any]]:
        obs = {name: value[0] for name, value in steps.observations.items()}
        info: dict[str, Any] = {
            "action_mask": steps.action_mask[0],
            "action_applied": int(steps.action_applied[0]),
            "reward_terms": {
                name: float(steps.reward_terms[0, i])
                for i, name in enumerate(self._remote.reward_terms)
            },
        }
        if steps.ended[0]:
            info["metrics"] = {
                name: float(steps.metrics[0, i])
                for i, name in enumerate(self._remote.metric_fields)
            }
        if steps.late[0]:
            info["late"] = True
        return obs, info

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        steps = self.group.reset((0,), (seed,))
        return self._unpack(steps)

    def step(self, action):
        actions = check_actions(action, 1, single=True)
        restarts = self.group.restarts
        steps = self.group.step(self.group.agents, actions)
        obs, info = self._unpack(steps)
        if self.group.restarts != restarts:
            info["server_restarted"] = True
        return (
            obs,
            float(steps.reward[0]),
            bool(steps.terminated[0]),
            bool(steps.truncated[0]),
            info,
        )

    def action_masks(self) -> np.ndarray:
        last = self.group.last
        assert last is not None
        return last.action_mask[0]

    def close(self) -> None:
        self._remote.close()


class RemoteHighwayVectorEnv(_RemoteHandles, gym.vector.VectorEnv):
    """``num_envs`` arenas of a remote server, stepped together (one message each way).

    ``parts`` > 1 opens the arenas as that many groups of consecutive environment indices
    (:attr:`part_slices`), each stepped by the server on its own, so that a trainer can overlap
    its work with the simulation, in the manner of EnvPool's ``send`` / ``recv``:
    :meth:`send` one part's actions, work on another part, :meth:`recv` the first. The
    arenas and their episodes are those of one group: reset with the same seed and given the
    same actions, every part of every step is the same as with ``parts=1`` (each arena has its
    own random stream). :meth:`step` sends every part, then receives every part.
    """

    metadata = {"render_modes": [], "autoreset_mode": _NEXT_STEP}  # noqa: RUF012

    def __init__(
        self,
        num_envs: int = 1,
        connect: str | Sequence[str] | None = None,
        preset: str = "min2018",
        overrides: Mapping[str, Scalar] | None = None,
        remote: RemoteConfig | None = None,
        render_mode: str | None = None,
        parts: int = 1,
    ) -> None:
        check_render_mode(render_mode, self.metadata["render_modes"])
        self._remote = _Remote(
            connect, remote, preset, overrides, arenas=num_envs, seed=None, parts=parts
        )
        spec = self._remote.spec
        self.num_envs = num_envs
        bounds = np.cumsum([0, *self._remote.part_sizes])
        self.part_slices = tuple(slice(int(a), int(b)) for a, b in itertools.pairwise(bounds))
        self.render_mode = None
        self.single_observation_space = spaces_from_spec(spec)
        self.single_action_space = spaces.Discrete(ACTION_COUNT)
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = spaces.MultiDiscrete(np.full(num_envs, ACTION_COUNT))
        self.decision_period_s = spec.decision_period_s
        self.max_episode_steps = spec.max_episode_steps
        self._part_restarts: dict[int, int] = {}

    def _info(self, steps: Steps) -> dict[str, Any]:
        info: dict[str, Any] = {
            "action_mask": steps.action_mask,
            "action_applied": steps.action_applied,
            "reward_terms": {
                name: steps.reward_terms[:, i] for i, name in enumerate(self._remote.reward_terms)
            },
            # The Steps' metrics are each episode's so far; the counts of events, as in-process.
            "episode_counts": {
                name: steps.metrics[:, self._remote.metric_fields.index(name)].astype(np.int64)
                for name in EPISODE_COUNTS
                if name in self._remote.metric_fields
            },
        }
        ended = steps.ended
        if ended.any():
            info["metrics"] = {
                name: np.where(ended, steps.metrics[:, i], 0.0)
                for i, name in enumerate(self._remote.metric_fields)
            }
            info["_metrics"] = ended
        if steps.late.any():
            info["late"] = steps.late
        return info

    def reset(
        self,
        *,
        seed: int | Sequence[int | None] | None = None,
        options: dict[str, Any] | None = None,
    ):
        seeds = arena_seeds(seed, self.num_envs)
        if seed is not None:
            self._np_random, self._np_random_seed = gym.utils.seeding.np_random(seeds[0])
        steps = [
            group.reset(tuple(range(part.stop - part.start)), tuple(seeds[part]))
            for group, part in zip(self._remote.groups, self.part_slices, strict=True)
        ]
        whole = _joined(steps)
        return dict(whole.observations), self._info(whole)

    def step(self, actions):
        actions = check_actions(actions, self.num_envs, single=False)
        restarts = [group.restarts for group in self._remote.groups]
        for group, part in zip(self._remote.groups, self.part_slices, strict=True):
            group.send(group.agents, actions[part])
        whole = _joined([group.receive() for group in self._remote.groups])
        info = self._info(whole)
        if [group.restarts for group in self._remote.groups] != restarts:
            info["server_restarted"] = np.ones(self.num_envs, dtype=bool)
        return (dict(whole.observations), whole.reward, whole.terminated, whole.truncated, info)

    def send(self, part: int, actions: np.ndarray) -> None:
        """Part ``part``'s actions (one per environment of :attr:`part_slices` [part]) go
        out; the server plays its round while the caller works. :meth:`recv` takes it."""
        part_slice = self._part_slice(part)
        actions = check_actions(actions, part_slice.stop - part_slice.start, single=False)
        group = self._remote.groups[part]
        self._part_restarts[part] = group.restarts
        group.send(group.agents, actions)

    def recv(self, part: int):
        """The step of part ``part`` that :meth:`send` started: ``(observations, rewards,
        terminated, truncated, info)`` of its environments, as :meth:`step` returns them for
        all."""
        part_slice = self._part_slice(part)
        group = self._remote.groups[part]
        steps = group.receive()
        info = self._info(steps)
        if group.restarts != self._part_restarts.get(part, group.restarts):
            info["server_restarted"] = np.ones(part_slice.stop - part_slice.start, dtype=bool)
        return (dict(steps.observations), steps.reward, steps.terminated, steps.truncated, info)

    def _part_slice(self, part: int) -> slice:
        if not 0 <= part < len(self.part_slices):
            raise ValueError(
                f"part must be between 0 and {len(self.part_slices) - 1} "
                f"(this environment has {len(self.part_slices)} part(s)), got {part}"
            )
        return self.part_slices[part]

    def close_extras(self, **kwargs: Any) -> None:
        # A constructor that raised (no server, every server full) leaves nothing to close;
        # gymnasium's __del__ calls close all the same.
        remote = getattr(self, "_remote", None)
        if remote is not None:
            remote.close()
