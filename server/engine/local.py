"""The simulator in this process, as an engine of overtake's environment faces.

An in-process environment plays the very rounds a server's arena groups play
(:class:`~overtake.server.engine.rounds.Rounds`: the autoreset, what each slot carries between
rounds), so that what it returns is the server's bit for bit; but it owns every car, so nothing of
the server's ledger is here (no trainer, ticket, message or deadline): its faces read the round's
rows (:class:`~overtake.server.engine.rounds.RoundRows`) straight from the simulator's arrays. What
only an in-process simulator has, its :class:`~overtake.envs.faces.Road` (world frames,
pictures, the privileged planner), is :class:`LocalRoad`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from overtake.envs.faces import PictureView, Simulator
from overtake.envs.registry import arena_seeds
from overtake.protocol import errors
from overtake.protocol.messages import BehaviourSpec, WorldFrame
from overtake.protocol.vocabulary import DEFAULT_ACTION

from ..sim import HighwaySim, SimConfig
from ..sim.config import as_json
from ..sim.planner import Planner
from ..sim.render import render_top_down
from .group_snapshot import GroupSnapshot
from .rounds import RoundRows, Rounds
from .spec import behaviour_spec
from .world import rounds_world_frame

IN_PROCESS = "in-process"
"""The server name in an in-process simulator's world frames."""


class LocalEngine:
    """``arenas`` arenas of ``config`` in this process, every car ours."""

    restarts = 0  # nothing to lose: the simulator lives here

    def __init__(self, config: SimConfig, arenas: int, agents_per_arena: int = 1) -> None:
        try:
            sim = HighwaySim(config, num_arenas=arenas, agents_per_arena=agents_per_arena)
        except ValueError as error:
            raise errors.BadConfig(str(error)) from None
        sim.reset(seeds=arena_seeds(None, arenas))
        self.rounds = Rounds(sim)
        self.spec: BehaviourSpec = behaviour_spec(sim)
        self._agents = np.arange(arenas * agents_per_arena, dtype=np.int32)
        self._every_car = np.ones((arenas, agents_per_arena), dtype=bool)
        self.trainer_step = -1
        self.frames_trainer_step = -1  # what world frames repeat: the step of the last round
        self._rows: RoundRows | None = None

    @property
    def sim(self) -> HighwaySim:
        return self.rounds.sim

    @property
    def agents(self) -> np.ndarray:
        return self._agents

    def reset(self, arenas: tuple[int, ...], seeds: tuple[int | None, ...]) -> RoundRows:
        count = self.rounds.shape[0]
        bad = [a for a in arenas if not 0 <= a < count]
        if bad:
            raise errors.UnknownArena(f"this simulator has arenas 0..{count - 1}, got {bad}")
        mine = np.ones(self.rounds.shape[1], dtype=bool)
        for arena, seed in zip(arenas, seeds, strict=True):
            self.rounds.reset_arena(arena, seed, mine, alone=True)
        self._rows = None
        return self.rounds.now()

    def send(self, agents: np.ndarray, actions: np.ndarray, retire: Sequence[int] = ()) -> None:
        if self._rows is not None:
            raise RuntimeError("actions sent twice for one round; receive its rows first")
        # The face checked the actions; every car is ours: the round is played directly, the
        # cars left out keep their lane (late), as a server plays a trainer's.
        if self.trainer_step >= 0:
            self.frames_trainer_step = self.trainer_step
        rounds = self.rounds
        if len(retire):
            rounds.retire(np.asarray(retire, dtype=np.int64))
        full = np.full(rounds.shape, DEFAULT_ACTION, dtype=np.int64)
        full.reshape(-1)[agents] = actions
        late = np.zeros(rounds.shape, dtype=bool)
        if agents.size < late.size:
            late[...] = True
            late.reshape(-1)[agents] = False
        self._rows = rounds.play(full, late, self._every_car)

    def receive(self) -> RoundRows:
        rows, self._rows = self._rows, None
        if rows is None:
            raise RuntimeError("no actions sent to receive a round for")
        return rows

    restorable = True  # the road lives here

    def snapshot(self) -> dict[str, Any]:
        """The arenas' whole state (:class:`~.group_snapshot.GroupSnapshot`) as plain data."""
        if self._rows is not None:
            raise RuntimeError("a snapshot between rounds only: receive the round sent for")
        return GroupSnapshot.of(self.rounds).to_plain()

    def restore(self, snapshot: Mapping[str, Any]) -> None:
        GroupSnapshot.from_plain(snapshot).restore_into(self.rounds)

    def snapshot_arenas(self, first: int, count: int) -> dict[str, Any]:
        """Arenas ``first`` .. ``first + count - 1`` alone, as an engine of ``count`` arenas of
        this configuration would :meth:`snapshot` them (:class:`~overtake.envs.shares`: a
        member's share of one engine keeps what it would keep alone)."""
        if self._rows is not None:
            raise RuntimeError("a snapshot between rounds only: receive the round sent for")
        return GroupSnapshot.of(self.rounds).arenas(first, count).to_plain()

    def restore_arenas(self, first: int, snapshot: Mapping[str, Any]) -> None:
        """Arenas ``first`` .. back as ``snapshot`` (:meth:`snapshot_arenas`, or a smaller
        engine's :meth:`snapshot`) found them; the others as they are (checked first)."""
        whole = GroupSnapshot.of(self.rounds)
        whole.with_arenas(first, GroupSnapshot.from_plain(snapshot)).restore_into(self.rounds)

    def close(self) -> None:
        """Nothing to release (the road lives in this process)."""


class LocalRoad:
    """The road of an in-process engine: world frames, pictures and the planner."""

    def __init__(self, engine: LocalEngine) -> None:
        self._engine = engine
        self._planner: Planner | None = None

    def world_frame(self, arena: int) -> WorldFrame:
        rounds = self._engine.rounds
        return rounds_world_frame(
            rounds,
            arena,
            rounds.latest_observations(),
            server=IN_PROCESS,
            group=0,
            arena_id=arena,
            trainer_step=self._engine.frames_trainer_step,
        )

    def picture(self, arena: int, view: PictureView | None = None) -> np.ndarray:
        if view is None:
            return render_top_down(self._engine.sim, arena=arena)
        return render_top_down(
            self._engine.sim,
            arena=arena,
            size_px=(view.width_px, view.height_px),
            pixels_per_m=view.pixels_per_m,
            centering=view.centering,
        )

    def planner_actions(self) -> np.ndarray:
        if self._planner is None:  # built on first use: most runs never ask
            self._planner = Planner(self._engine.sim)
        return self._planner.act().reshape(-1)


def local_simulator(config: SimConfig, arenas: int, agents_per_arena: int = 1) -> Simulator:
    """``arenas`` arenas of ``config`` in this process, one engine, with their road."""
    engine = LocalEngine(config, arenas, agents_per_arena)
    return Simulator(
        parts=(engine,),
        spec=engine.spec,
        sim_config=as_json(config),
        road=LocalRoad(engine),
    )


__all__ = ["IN_PROCESS", "LocalEngine", "LocalRoad", "local_simulator"]
