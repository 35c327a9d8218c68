"""Arena groups: the unit the server steps. No Zenoh here, only the simulation and bookkeeping.

The arenas one open request creates form a group, one :class:`HighwaySim` stepped in one
numpy pass. Each agent slot of each arena is owned by at most one trainer. A group steps
(a *round*) when every trainer that owns a car in it has sent its actions for the round, or,
once somebody has, at the deadline, with the default action for whoever is late.

A group is two rooms: the ledger of its trainers here (claims, tickets, pending actions, the
deadline, the late count, rates) and the road's :class:`~.rounds.Rounds`, which the in-process
engine plays directly. Episodes end per agent and restart on the next round (Gymnasium's
next-step autoreset): an arena with one agent is reset whole, so a remote arena reproduces an
in-process one bit for bit; in a shared arena only the agent that ended restarts (it is taken
off the road for the round and placed back afterwards) while the road goes on for the others.
"""

from __future__ import annotations

import itertools
import secrets
import time
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from overtake.envs.registry import arena_seeds
from overtake.protocol import errors
from overtake.protocol.messages import (
    MAX_FRAME_BYTES,
    Actions,
    BehaviourSpec,
    GroupStatus,
    Scalar,
    Steps,
    Translation,
)
from overtake.protocol.vocabulary import DEFAULT_ACTION

from ..engine.requested import resolve_config
from ..engine.rounds import Rounds
from ..engine.spec import behaviour_spec
from ..sim import HighwaySim, SimConfig
from .members import Member

# Group steps taken in this process, in order: what next_to_step compares.
_GROUP_STEPS = itertools.count(1)


@dataclass
class Group:
    group_id: int
    server: str
    arena_ids: list[int]
    preset: str
    sim: HighwaySim
    spec: BehaviourSpec
    members: dict[str, Member] = field(default_factory=dict)
    deadline: float | None = None  # monotonic time the current round gives up waiting
    late_agents: int = 0
    rounds_done: int = 0
    rate_rounds_per_s: float = 0.0
    _last_round_t: float = field(default_factory=time.monotonic)
    # The step count a member last sent with its actions (-1: none has), for world frames.
    trainer_step: int = -1
    # The process's count of group steps at this group's last step (0: not yet stepped); the
    # server steps the ready group with the lowest first (next_to_step).
    last_stepped: int = 0
    # The road's rounds and what each agent slot carries between them (whose episode ended,
    # the cars their trainer retired, what each got last round).
    rounds: Rounds = field(init=False)

    def __post_init__(self) -> None:
        self.rounds = Rounds(self.sim)

    @property
    def round(self) -> int:
        """The protocol's round counter: rounds played."""
        return self.rounds.round

    @property
    def ended(self) -> np.ndarray:
        return self.rounds.ended

    @property
    def retired(self) -> np.ndarray:
        return self.rounds.retired

    @classmethod
    def open(
        cls,
        group_id: int,
        server: str,
        arena_ids: list[int],
        preset: str,
        overrides: Mapping[str, Scalar],
        agents_per_arena: int,
        seed: int | None,
        as_recorded: str = "",
        observations: tuple[str, ...] = (),
        ego_fields: tuple[str, ...] = (),
        translation: Translation | None = None,
    ) -> Group:
        config = resolve_config(
            preset, overrides, as_recorded, observations, ego_fields, translation
        )
        return cls.of_config(group_id, server, arena_ids, config, agents_per_arena, seed)

    @classmethod
    def of_config(
        cls,
        group_id: int,
        server: str,
        arena_ids: list[int],
        config: SimConfig,
        agents_per_arena: int,
        seed: int | None,
    ) -> Group:
        """A group of arenas running ``config``, every car off the road until claimed."""
        try:
            sim = HighwaySim(config, num_arenas=len(arena_ids), agents_per_arena=agents_per_arena)
        except ValueError as error:
            raise errors.BadConfig(str(error)) from None
        # One trainer's Steps carry all its agents' observations: they must fit in a frame.
        per_agent = sum(
            int(np.prod(box.shape)) * box.dtype.itemsize
            for box in sim.observation_spaces().values()
        )
        step_bytes = per_agent * sim.num_arenas * sim.agents
        if step_bytes > MAX_FRAME_BYTES // 2:
            raise errors.BadConfig(
                f"{sim.num_arenas} arena(s) x {sim.agents} agent(s) x {per_agent} bytes of "
                f"observations is {step_bytes} bytes a step, over the limit of "
                f"{MAX_FRAME_BYTES // 2}: open fewer arenas at once or use smaller images"
            )
        sim.reset(seeds=arena_seeds(seed, len(arena_ids)))
        group = cls(
            group_id=group_id,
            server=server,
            arena_ids=list(arena_ids),
            preset=config.preset,
            sim=sim,
            spec=behaviour_spec(sim),
        )
        # Every car starts off the road; claims put them on.
        for arena in range(sim.num_arenas):
            sim.remove_agents(arena, np.arange(sim.agents))
        return group

    # --- membership -----------------------------------------------------------------------

    @property
    def shape(self) -> tuple[int, int]:
        return self.sim.num_arenas, self.sim.agents

    def owned(self) -> np.ndarray:
        taken = np.zeros(self.shape, dtype=bool)
        for member in self.members.values():
            taken |= member.slots
        return taken

    def claim(self, trainer: str, arena_index: int, count: int, *, fresh: bool) -> None:
        """Give ``trainer`` ``count`` free slots of one arena and put their cars on the road.

        ``fresh``: the arena was just reset, so the cars keep their reset places.
        """
        free = np.flatnonzero(~self.owned()[arena_index])
        if free.size < count:
            raise errors.ServerFull(
                f"arena {self.arena_ids[arena_index]} has {free.size} free agent slot(s) of "
                f"{self.sim.agents}, asked for {count}"
            )
        slots = free[:count]
        member = self.members.get(trainer)
        if member is None:
            member = self.members[trainer] = Member(
                ticket=secrets.token_bytes(16), slots=np.zeros(self.shape, dtype=bool)
            )
        member.slots[arena_index, slots] = True
        member.count = int(member.slots.sum())
        if fresh:
            self.sim.restore_agents(arena_index, slots)
        else:
            self.sim.respawn_agents(arena_index, slots)
        claimed = np.zeros(self.shape, dtype=bool)
        claimed[arena_index, slots] = True
        self.rounds.clear(claimed)

    def leave(self, trainer: str) -> None:
        """Take ``trainer``'s cars off the road; its pending actions are dropped."""
        member = self.members.pop(trainer, None)
        if member is None:
            return
        for arena, slot in zip(*np.nonzero(member.slots), strict=True):
            self.sim.remove_agents(int(arena), [int(slot)])
        # A car that ended its episode just before its trainer left must not come back.
        self.rounds.clear(member.slots)
        if not any(m.pending is not None for m in self.members.values()):
            self.deadline = None

    def member(self, trainer: str, ticket: bytes) -> Member:
        member = self.members.get(trainer)
        if member is None:
            raise errors.NotOwner(
                f"trainer {trainer!r} has no agents in group {self.group_id} "
                f"(arenas {self.arena_ids}); open or join an arena first"
            )
        if not secrets.compare_digest(member.ticket, ticket):
            raise errors.WrongTicket(
                f"wrong ticket for trainer {trainer!r} in group "
                f"{self.group_id}: requests must come from the session "
                "that opened or joined it"
            )
        return member

    # --- rounds -----------------------------------------------------------------------------

    def accept(self, actions: Actions, deadline_s: float) -> None:
        """Hold a trainer's actions for the current round (checked against what it owns)."""
        member = self.member(actions.trainer, actions.ticket)
        member.check(actions, self.group_id, self.round)
        member.pending = actions
        if actions.trainer_step >= 0:
            self.trainer_step = actions.trainer_step
        if self.deadline is None:
            self.deadline = time.monotonic() + deadline_s

    def ready(self, now: float) -> bool:
        if not self.members:
            return False
        if all(m.pending is not None for m in self.members.values()):
            return True
        return self.deadline is not None and now >= self.deadline

    def step(self) -> dict[str, Steps]:
        """Run one round; returns each member's :class:`Steps`."""
        self.last_stepped = next(_GROUP_STEPS)
        arenas, n = self.shape
        actions = np.full((arenas, n), DEFAULT_ACTION, dtype=np.int64)
        late = np.zeros((arenas, n), dtype=bool)
        for member in self.members.values():
            if member.pending is not None and member.pending.retire is not None:
                self._retire(member.pending.retire)
        # Whoever has no action (its trainer late, or it left the car out) keeps its lane.
        for member in self.members.values():
            pending, member.pending = member.pending, None
            if pending is None:
                late |= member.slots
                continue
            actions.reshape(-1)[pending.agents] = pending.actions
            # Its agents are distinct and its own (accept), so all of them when as many.
            if pending.agents.size < member.count:
                left_out = member.slots.copy()
                left_out.reshape(-1)[pending.agents] = False
                late |= left_out
        return self._play(actions, late)

    def _play(self, actions: np.ndarray, late: np.ndarray) -> dict[str, Steps]:
        """The round itself: every member's ``actions`` (A, N), whose are missing ``late``."""
        some_late = bool(late.any())
        rows = self.rounds.play(actions, late, self.owned())
        if some_late:  # (those the round found not late are not counted)
            self.late_agents += int(rows.late.sum())
        self.rounds_done += 1
        self.deadline = None
        now = time.monotonic()
        dt = max(now - self._last_round_t, 1e-9)
        self._last_round_t = now
        self.rate_rounds_per_s = (
            1.0 / dt if self.rounds_done == 1 else 0.9 * self.rate_rounds_per_s + 0.1 / dt
        )
        return {
            trainer: member.steps(rows, self.server, self.group_id, self.round)
            for trainer, member in self.members.items()
        }

    def _retire(self, agents: np.ndarray) -> None:
        self.rounds.retire(agents)

    def reset(
        self,
        trainer: str,
        ticket: bytes,
        arena_indices: tuple[int, ...],
        seeds: tuple[int | None, ...],
    ) -> Steps:
        """Restart episodes in some arenas for ``trainer``; returns its :class:`Steps`."""
        member = self.member(trainer, ticket)
        arenas = self.shape[0]
        bad = [a for a in arena_indices if not 0 <= a < arenas]
        if bad:
            raise errors.UnknownArena(
                f"group {self.group_id} has arenas 0..{arenas - 1} "
                f"(ids {self.arena_ids}), got indices {bad}"
            )
        owned = self.owned()
        for arena, seed in zip(arena_indices, seeds, strict=True):
            mine = member.slots[arena]
            if not mine.any():
                raise errors.NotOwner(
                    f"trainer {trainer!r} has no agents in arena {self.arena_ids[arena]}"
                )
            # Alone on this road: a real reset, seeded as asked; else only its cars restart.
            self.rounds.reset_arena(arena, seed, mine, alone=bool((owned[arena] == mine).all()))
        member.pending = None
        if not any(m.pending is not None for m in self.members.values()):
            self.deadline = None
        return self.current_steps(trainer)

    def current_steps(self, trainer: str) -> Steps:
        """The trainer's agents as they are now (after a claim), reward 0, no flags."""
        return self.members[trainer].steps(
            self.rounds.now(), self.server, self.group_id, self.round
        )

    # --- views ------------------------------------------------------------------------------

    def status(self) -> GroupStatus:
        return GroupStatus(
            group=self.group_id,
            preset=self.preset,
            arenas=tuple(self.arena_ids),
            agents_per_arena=self.sim.agents,
            trainers=tuple(sorted(self.members)),
            rounds=self.rounds_done,
            rounds_per_s=float(self.rate_rounds_per_s),
            agent_steps_per_s=float(self.rate_rounds_per_s * int(self.owned().sum())),
            late_agents=self.late_agents,
        )

    def latest_observations(self) -> dict[str, np.ndarray]:
        """Every agent's observation of the last round (observed now before the first)."""
        return self.rounds.latest_observations()
