"""One engine's arenas shared by several vector environments, each a face of its own.

A members' batch (``overtake-train --seeds``) trains several runs in one process; each run has
its own environment, but stepping every run's arenas in one engine costs one simulator call a
round instead of one a run. :func:`share_face` cuts one face's engine into shares of
consecutive arenas: each share is an :class:`~.faces.Engine` whose agents, rows and snapshots
are those an engine of its arenas alone would have (agent ids from 0, a snapshot of its arenas
only), so a run cannot tell its share from an engine of its own, and a run's checkpoint made on
a share resumes on an engine of its own and the other way round.

A round is played once, when the first share that sent actions asks for it (every share sends
before any receives, as a vector environment's parts do): every share that sent is in it. A
share that sent nothing sits the round out: its arenas are kept when it begins to and put back
when it next acts, keeps or is shown (stepped meanwhile with nobody's actions, their rows
dropped), so they are as they were, as an engine of their own that is not stepped stays (a
member already at its budget waits so, perhaps for many rounds). Each arena has its own random
stream and no simulator array mixes arenas, so a share's arenas step exactly as they would alone
(``tests/envs/test_shares.py``).
"""

from __future__ import annotations

import dataclasses
import itertools
from collections.abc import Mapping, Sequence
from typing import Any, Protocol, runtime_checkable

import numpy as np

from overtake.protocol.messages import WorldFrame
from overtake.protocol.rows import Rows

from .faces import Engine, PictureView, Restorable, Road, Simulator, VectorFace


@runtime_checkable
class ArenaRestorable(Protocol):
    """An engine that keeps and puts back some of its arenas alone (the in-process engine)."""

    def snapshot_arenas(self, first: int, count: int) -> dict[str, Any]: ...

    def restore_arenas(self, first: int, snapshot: Mapping[str, Any]) -> None: ...


@dataclasses.dataclass
class _Sent:
    agents: np.ndarray  # the engine's agent ids
    actions: np.ndarray
    retire: np.ndarray  # the engine's agent ids


class SharedEngine:
    """The engine under the shares (:func:`share_face`): it plays a round when a share that
    sent asks for it, with every share that sent, and hands each its rows."""

    def __init__(self, engine: Engine, arenas: Sequence[int]) -> None:
        if not arenas or min(arenas) < 1:
            raise ValueError(f"each share needs at least one arena, got {list(arenas)}")
        total = sum(arenas)
        agents = len(engine.agents)
        if agents % total:
            raise ValueError(f"the engine's {agents} agents do not fill {total} arenas evenly")
        self.engine = engine
        self.agents_per_arena = agents // total
        first_arenas = [0, *itertools.accumulate(arenas)][:-1]
        self.shares = tuple(
            EngineShare(self, k, first, count)
            for k, (first, count) in enumerate(zip(first_arenas, arenas, strict=True))
        )
        self._sent: dict[int, _Sent] = {}  # the next round's actions, by share
        self._played: dict[int, Rows] = {}  # a round's rows its senders have not taken yet
        # The arenas of shares sitting rounds out, as they were when they began to: put back
        # when the share next acts, not after every round it sits out (a member at its budget
        # may wait for many rounds).
        self._kept: dict[int, dict[str, Any]] = {}
        self._open = len(self.shares)

    def send(self, share: EngineShare, sent: _Sent) -> None:
        if not self.between_rounds(share):
            raise RuntimeError("actions sent twice for one round; receive its rows first")
        self.wake(share)
        self._sent[share.index] = sent

    def receive(self, share: EngineShare) -> Rows:
        if share.index not in self._played:
            if share.index not in self._sent:
                raise RuntimeError("no actions sent to receive a round for")
            self._play()
        return self._played.pop(share.index)

    def _play(self) -> None:
        sent, self._sent = self._sent, {}
        # The shares that begin to sit out now (those already sitting out stay kept).
        sitting = [
            s
            for s in self.shares
            if s.index not in sent and s.index not in self._kept and not s.closed
        ]
        if sitting:
            keeper = self.engine
            if not isinstance(keeper, ArenaRestorable):
                self._sent = sent
                raise RuntimeError(
                    f"shares {[s.index for s in sitting]} sent no actions for this round, and "
                    "this engine cannot keep their arenas as they are: every share must send"
                )
            for s in sitting:
                self._kept[s.index] = keeper.snapshot_arenas(s.first_arena, s.arenas)
        order = sorted(sent)
        retire = np.concatenate([sent[k].retire for k in order])
        self.engine.trainer_step = max(self.shares[k].trainer_step for k in order)
        self.engine.send(
            np.concatenate([sent[k].agents for k in order]),
            np.concatenate([sent[k].actions for k in order]),
            retire.tolist(),
        )
        rows = self.engine.receive()
        for k in order:
            self._played[k] = self.shares[k].own_rows(rows)

    def between_rounds(self, share: EngineShare) -> bool:
        return share.index not in self._sent and share.index not in self._played

    def wake(self, share: EngineShare) -> None:
        """Put back the arenas ``share`` had when it began to sit rounds out (they were
        stepped meanwhile, with nobody's actions), before it acts, keeps or is shown again."""
        snapshot = self._kept.pop(share.index, None)
        if snapshot is not None:
            engine = self.engine
            assert isinstance(engine, ArenaRestorable)
            engine.restore_arenas(share.first_arena, snapshot)

    def forget_kept(self, share: EngineShare) -> None:
        """``share``'s arenas are about to be written whole (a restore): nothing to put back."""
        self._kept.pop(share.index, None)

    def close(self, share: EngineShare) -> None:
        self._sent.pop(share.index, None)
        self._played.pop(share.index, None)
        self._kept.pop(share.index, None)
        self._open -= 1
        if self._open == 0:
            self.engine.close()


class EngineShare:
    """Arenas ``first_arena`` .. of a :class:`SharedEngine`, as an engine of their own
    (:class:`~.faces.Engine`, :class:`~.faces.Restorable` where the engine keeps arenas)."""

    def __init__(self, shared: SharedEngine, index: int, first_arena: int, arenas: int) -> None:
        self.shared = shared
        self.index = index
        self.first_arena = first_arena
        self.arenas = arenas
        per = shared.agents_per_arena
        self._first_agent = first_arena * per
        self._agents = np.arange(arenas * per, dtype=np.int32)
        self.trainer_step = -1
        self.closed = False

    @property
    def agents(self) -> np.ndarray:
        return self._agents

    @property
    def restarts(self) -> int:
        """The engine's: a lost server truncates every share's episodes."""
        return self.shared.engine.restarts

    @restarts.setter
    def restarts(self, count: int) -> None:
        self.shared.engine.restarts = count

    @property
    def restorable(self) -> bool:
        engine = self.shared.engine
        return (
            isinstance(engine, Restorable)
            and engine.restorable
            and isinstance(engine, ArenaRestorable)
        )

    def own_rows(self, rows: Rows) -> Rows:
        """This share's rows of the engine's ``rows``, its agent ids from 0."""
        lo, hi = self._first_agent, self._first_agent + self._agents.size
        mine = np.flatnonzero((rows.agents >= lo) & (rows.agents < hi))
        # Consecutive rows (the in-process engine's, always) are taken as views.
        index: slice | np.ndarray = mine
        if mine.size and mine[-1] - mine[0] + 1 == mine.size:
            index = slice(int(mine[0]), int(mine[-1]) + 1)
        values = rows.taken(index)
        values["agents"] = (rows.agents[index] - lo).astype(np.int32)
        return dataclasses.replace(rows, **values)

    def reset(self, arenas: tuple[int, ...], seeds: tuple[int | None, ...]) -> Rows:
        if not self.shared.between_rounds(self):
            raise RuntimeError("a reset between rounds only: receive the round sent for")
        bad = [a for a in arenas if not 0 <= a < self.arenas]
        if bad:
            raise ValueError(f"this share has arenas 0..{self.arenas - 1}, got {bad}")
        self.shared.wake(self)
        rows = self.shared.engine.reset(tuple(self.first_arena + a for a in arenas), seeds)
        return self.own_rows(rows)

    def send(self, agents: np.ndarray, actions: np.ndarray, retire: Sequence[int] = ()) -> None:
        agents = np.asarray(agents)
        if agents.size and (agents.min() < 0 or agents.max() >= self._agents.size):
            raise ValueError(f"this share's agents are 0..{self._agents.size - 1}")
        self.shared.send(
            self,
            _Sent(
                agents=agents.astype(np.int64) + self._first_agent,
                actions=np.asarray(actions),
                retire=np.asarray(retire, dtype=np.int64) + self._first_agent,
            ),
        )

    def receive(self) -> Rows:
        return self.shared.receive(self)

    def snapshot(self) -> dict[str, Any]:
        """This share's arenas alone, as an engine of them alone would snapshot them."""
        if not self.restorable:
            raise TypeError("this engine cannot keep some of its arenas alone")
        if not self.shared.between_rounds(self):
            raise RuntimeError("a snapshot between rounds only: receive the round sent for")
        engine = self.shared.engine
        assert isinstance(engine, ArenaRestorable)
        self.shared.wake(self)
        return engine.snapshot_arenas(self.first_arena, self.arenas)

    def restore(self, snapshot: Mapping[str, Any]) -> None:
        """This share's arenas back as ``snapshot`` (this share's, or an engine's of as many
        arenas alone) found them; the other shares' as they are."""
        if not self.restorable:
            raise TypeError("this engine cannot put back some of its arenas alone")
        engine = self.shared.engine
        assert isinstance(engine, ArenaRestorable)
        self.shared.forget_kept(self)
        engine.restore_arenas(self.first_arena, snapshot)

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            self.shared.close(self)


class RoadShare:
    """A share's arenas of the engine's road, numbered from 0 (:class:`~.faces.Road`)."""

    def __init__(self, road: Road, share: EngineShare) -> None:
        self._road = road
        self._share = share

    def world_frame(self, arena: int) -> WorldFrame:
        frame = self._road.world_frame(self._share.first_arena + self._arena(arena))
        return dataclasses.replace(frame, arena=arena)

    def picture(self, arena: int, view: PictureView | None = None) -> np.ndarray:
        return self._road.picture(self._share.first_arena + self._arena(arena), view)

    def planner_actions(self) -> np.ndarray:
        share = self._share
        share.shared.wake(share)
        first = share.first_arena * share.shared.agents_per_arena
        return self._road.planner_actions()[first : first + share.agents.size]

    def _arena(self, arena: int) -> int:
        if not 0 <= arena < self._share.arenas:
            raise ValueError(f"this share has arenas 0..{self._share.arenas - 1}, got {arena}")
        self._share.shared.wake(self._share)  # shown as it stands, not as stepped meanwhile
        return arena


def share_face(face: VectorFace, arenas: Sequence[int]) -> tuple[VectorFace, ...]:
    """``face``'s arenas (one engine's) as consecutive shares of ``arenas`` arenas each, a
    vector environment each (as many environments as the share has agents). The shares own
    the engine from here: ``face`` is not stepped again, and the engine is closed with the
    last share."""
    simulator = face.simulator
    if len(simulator.parts) != 1:
        raise ValueError(f"a face of one engine is shared, this one has {len(simulator.parts)}")
    shared = SharedEngine(simulator.parts[0], arenas)
    return tuple(
        VectorFace(
            Simulator(
                parts=(share,),
                spec=simulator.spec,
                sim_config=simulator.sim_config,
                road=None if simulator.road is None else RoadShare(simulator.road, share),
            ),
            num_envs=share.agents.size,
            render_mode=face.render_mode,
        )
        for share in shared.shares
    )


__all__ = ["ArenaRestorable", "EngineShare", "RoadShare", "SharedEngine", "share_face"]
