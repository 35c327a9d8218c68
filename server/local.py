"""The simulator in this process, as an engine of overtake's environment faces.

An in-process environment steps the very arena group a server steps for its trainers
(:class:`~overtake.server.groups.Group`, one member that owns every car), so that its Steps,
and with them everything an environment returns, are the server's bit for bit. What only an
in-process simulator has, its :class:`~overtake.protocol.faces.Road` (world frames, pictures,
the privileged planner), is :class:`LocalRoad`.
"""

from __future__ import annotations

import dataclasses
import json
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from overtake.protocol.faces import Simulator
from overtake.protocol.messages import Steps, WorldFrame

from .group_snapshot import GroupSnapshot
from .groups import Group
from .sim import HighwaySim, SimConfig
from .sim.planner import Planner
from .sim.render import render_top_down
from .world import group_world_frame

IN_PROCESS = "in-process"
"""The server name in an in-process simulator's Steps and world frames."""
_TRAINER = "in-process"


class LocalEngine:
    """A group of ``arenas`` arenas of ``config`` in this process, every car ours."""

    restarts = 0  # nothing to lose: the simulator lives here

    def __init__(self, config: SimConfig, arenas: int, agents_per_arena: int = 1) -> None:
        self.group = Group.of_config(
            0, IN_PROCESS, list(range(arenas)), config, agents_per_arena, seed=None
        )
        for arena in range(arenas):
            self.group.claim(_TRAINER, arena, agents_per_arena, fresh=True)
        self._ticket = self.group.members[_TRAINER].ticket
        self._agents = np.arange(arenas * agents_per_arena, dtype=np.int32)
        self.trainer_step = -1
        self._steps: Steps | None = None

    @property
    def sim(self) -> HighwaySim:
        return self.group.sim

    @property
    def agents(self) -> np.ndarray:
        return self._agents

    def reset(self, arenas: tuple[int, ...], seeds: tuple[int | None, ...]) -> Steps:
        return self.group.reset(_TRAINER, self._ticket, arenas, seeds)

    def send(self, agents: np.ndarray, actions: np.ndarray, retire: Sequence[int] = ()) -> None:
        if self._steps is not None:
            raise RuntimeError("actions sent twice for one round; receive its Steps first")
        # The face checked the actions; every car is ours: the round is played directly.
        if self.trainer_step >= 0:  # what world frames repeat (Actions.trainer_step remotely)
            self.group.trainer_step = self.trainer_step
        self._steps = self.group.play_alone(
            np.asarray(agents, dtype=np.int64),
            np.asarray(actions, dtype=np.int64),
            np.asarray(retire, dtype=np.int32),
        )

    def receive(self) -> Steps:
        steps, self._steps = self._steps, None
        if steps is None:
            raise RuntimeError("no actions sent to receive Steps for")
        return steps

    restorable = True  # the road lives here

    def snapshot(self) -> dict[str, Any]:
        """The arenas' whole state (:class:`~.group_snapshot.GroupSnapshot`) as plain data."""
        if self._steps is not None:
            raise RuntimeError("a snapshot between rounds only: receive the Steps sent for")
        return GroupSnapshot.of(self.group).to_plain()

    def restore(self, snapshot: Mapping[str, Any]) -> None:
        GroupSnapshot.from_plain(snapshot).restore_into(self.group)

    def close(self) -> None:
        """Nothing to release (the road lives in this process)."""


class LocalRoad:
    """The road of an in-process engine: world frames, pictures and the planner."""

    def __init__(self, engine: LocalEngine) -> None:
        self._engine = engine
        self._planner: Planner | None = None

    def world_frame(self, arena: int) -> WorldFrame:
        group = self._engine.group
        return group_world_frame(group, arena, group.latest_observations())

    def picture(self, arena: int) -> np.ndarray:
        return render_top_down(self._engine.sim, arena=arena)

    def planner_actions(self) -> np.ndarray:
        if self._planner is None:  # built on first use: most runs never ask
            self._planner = Planner(self._engine.sim)
        return self._planner.act().reshape(-1)


def local_simulator(config: SimConfig, arenas: int, agents_per_arena: int = 1) -> Simulator:
    """``arenas`` arenas of ``config`` in this process, one engine, with their road."""
    engine = LocalEngine(config, arenas, agents_per_arena)
    return Simulator(
        parts=(engine,),
        spec=engine.group.spec,
        sim_config=json.loads(json.dumps(dataclasses.asdict(config))),
        road=LocalRoad(engine),
    )


__all__ = ["IN_PROCESS", "LocalEngine", "LocalRoad", "local_simulator"]
