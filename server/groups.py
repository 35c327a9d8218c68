"""Arena groups: the unit the server steps. No Zenoh here, only the simulation and bookkeeping.

The arenas one open request creates form a group, one :class:`HighwaySim` stepped in one
numpy pass. Each agent slot of each arena is owned by at most one trainer. A group steps
(a *round*) when every trainer that owns a car in it has sent its actions for the round, or,
once somebody has, at the deadline, with the default action for whoever is late.

Episodes end per agent and restart on the next round (Gymnasium's next-step autoreset), in
:func:`~overtake.server.sim.autoreset_round`, the round the in-process vector environment
steps too: an arena with one agent is reset whole, so a remote arena reproduces an in-process
one bit for bit; in a shared arena only the agent that ended restarts (it is taken off the road
for the round and placed back afterwards) while the road goes on for the others.
"""

from __future__ import annotations

import itertools
import secrets
import time
from collections.abc import Mapping
from dataclasses import dataclass, field

import numpy as np

from overtake.protocol import errors
from overtake.protocol.envs import arena_seeds
from overtake.protocol.messages import (
    MAX_FRAME_BYTES,
    Actions,
    BehaviourSpec,
    GroupStatus,
    Scalar,
    Steps,
)
from overtake.protocol.vocabulary import (
    DEFAULT_ACTION,
)

from .sim import PRESETS, ConfigError, HighwaySim, SimConfig, autoreset_round, make_config
from .spec import behaviour_spec


def resolve_config(preset: str, overrides: Mapping[str, Scalar]) -> SimConfig:
    if preset not in PRESETS:
        raise errors.UnknownPreset(
            f"unknown preset {preset!r}: this server has {', '.join(sorted(PRESETS))}"
        )
    try:
        return make_config(preset, overrides)
    except ConfigError as error:
        raise errors.BadConfig(str(error)) from None


@dataclass
class Member:
    """A trainer's stake in a group."""

    ticket: bytes
    slots: np.ndarray  # (A, N) bool: the agent slots it owns
    pending: Actions | None = None  # its actions for the current round
    count: int = 0  # how many slots it owns (slots.sum())


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
    round: int = 0
    deadline: float | None = None  # monotonic time the current round gives up waiting
    late_agents: int = 0
    rounds_done: int = 0
    rate_rounds_per_s: float = 0.0
    _last_round_t: float = field(default_factory=time.monotonic)
    last_observations: dict[str, np.ndarray] | None = None  # of the last round, for spectators
    # The step count a member last sent with its actions (-1: none has), for world frames.
    trainer_step: int = -1
    # The process's count of group steps at this group's last step (0: not yet stepped); the
    # server steps the ready group with the lowest first (next_to_step).
    last_stepped: int = 0
    # (A, N) per agent slot: whose episode ended last round, and what it got then.
    ended: np.ndarray = field(init=False)
    # (A, N): cars their trainer took off the road (Actions.retire) until it resets the arena.
    retired: np.ndarray = field(init=False)
    last_reward: np.ndarray = field(init=False)
    last_applied: np.ndarray = field(init=False)
    last_terms: np.ndarray = field(init=False)  # (A, N, reward terms)

    def __post_init__(self) -> None:
        shape = (self.sim.num_arenas, self.sim.agents)
        self.ended = np.zeros(shape, dtype=bool)
        self.retired = np.zeros(shape, dtype=bool)
        self.last_reward = np.zeros(shape)
        self.last_applied = np.full(shape, -1, dtype=np.int64)
        self.last_terms = np.zeros(shape + (len(self.sim.reward_terms),))

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
    ) -> Group:
        config = resolve_config(preset, overrides)
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
        self.ended[arena_index, slots] = False
        self.retired[arena_index, slots] = False
        self.last_reward[arena_index, slots] = 0.0
        self.last_applied[arena_index, slots] = -1
        self.last_terms[arena_index, slots] = 0.0

    def leave(self, trainer: str) -> None:
        """Take ``trainer``'s cars off the road; its pending actions are dropped."""
        member = self.members.pop(trainer, None)
        if member is None:
            return
        for arena, slot in zip(*np.nonzero(member.slots), strict=True):
            self.sim.remove_agents(int(arena), [int(slot)])
        # A car that ended its episode just before its trainer left must not come back.
        self.ended &= ~member.slots
        self.retired &= ~member.slots
        self.last_reward[member.slots] = 0.0
        self.last_applied[member.slots] = -1
        self.last_terms[member.slots] = 0.0
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
        if actions.round < self.round:
            raise errors.StaleActions(
                f"actions answer round {actions.round}, but group "
                f"{self.group_id} played it at the deadline and is at "
                f"round {self.round}"
            )
        if actions.round > self.round:
            raise errors.BadAction(
                f"actions answer round {actions.round}, but group "
                f"{self.group_id} is only at round {self.round}"
            )
        agents = actions.agents
        total = self.sim.num_arenas * self.sim.agents
        if agents.size and (agents.min() < 0 or agents.max() >= total):
            raise errors.BadAction(
                f"agent ids in group {self.group_id} are 0..{total - 1}, got "
                f"{agents[(agents < 0) | (agents >= total)].tolist()}"
            )
        mine = member.slots.reshape(-1)[agents]
        if not mine.all():
            raise errors.NotOwner(
                f"agents {agents[~mine].tolist()} of group {self.group_id} "
                f"belong to another trainer or to nobody; "
                f"{actions.trainer!r} owns "
                f"{np.flatnonzero(member.slots).tolist()}"
            )
        if actions.retire is not None and actions.retire.size:
            retire = actions.retire
            if retire.min() < 0 or retire.max() >= total:
                raise errors.BadAction(
                    f"agent ids in group {self.group_id} are 0..{total - 1}, asked to retire "
                    f"{retire[(retire < 0) | (retire >= total)].tolist()}"
                )
            theirs = ~member.slots.reshape(-1)[retire]
            if theirs.any():
                raise errors.NotOwner(
                    f"agents {retire[theirs].tolist()} of group {self.group_id} belong to "
                    f"another trainer or to nobody; {actions.trainer!r} may retire only its "
                    f"own, {np.flatnonzero(member.slots).tolist()}"
                )
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

    def play_alone(self, agents: np.ndarray, actions: np.ndarray, retire: np.ndarray) -> Steps:
        """:meth:`step`'s round for an in-process engine, owner of every car: its face checked
        ``agents``' actions (the others keep their lane, late); no message, ticket, deadline."""
        self.last_stepped = next(_GROUP_STEPS)
        if retire.size:
            self._retire(retire)
        full = np.full(self.shape, DEFAULT_ACTION, dtype=np.int64)
        full.reshape(-1)[agents] = actions
        late = np.zeros(self.shape, dtype=bool)
        if agents.size < late.size:
            late[...] = True
            late.reshape(-1)[agents] = False
        (trainer,) = self.members
        return self._play(full, late)[trainer]

    def _play(self, actions: np.ndarray, late: np.ndarray) -> dict[str, Steps]:
        """The round itself: every member's ``actions`` (A, N), whose are missing ``late``."""
        sim = self.sim
        arenas, n = self.shape
        if late.any():
            late &= ~self.ended & ~self.retired
            self.late_agents += int(late.sum())

        result = autoreset_round(sim, actions, self.ended & self.owned(), sim.agents_present())
        # Filled column by column: np.stack costs more than the copy on arrays this small.
        terms = np.empty((arenas, n, len(sim.reward_terms)))
        for i, name in enumerate(sim.reward_terms):
            terms[..., i] = result.reward_terms[name]
        self.ended = result.ended
        self.last_reward, self.last_applied, self.last_terms = (
            result.reward,
            result.action_applied,
            terms,
        )
        self.round += 1
        self.rounds_done += 1
        self.deadline = None
        now = time.monotonic()
        dt = max(now - self._last_round_t, 1e-9)
        self._last_round_t = now
        self.rate_rounds_per_s = (
            1.0 / dt if self.rounds_done == 1 else 0.9 * self.rate_rounds_per_s + 0.1 / dt
        )
        return self._steps_for_members(
            result.reward, result.terminated, result.truncated, result.action_applied, late, terms
        )

    def _retire(self, agents: np.ndarray) -> None:
        """Take cars off the road before a round; they stay off, not restarted, until their
        arena is reset (a car that just ended is not restarted either)."""
        slots = np.zeros(self.shape, dtype=bool)
        slots.reshape(-1)[agents] = True
        fresh = slots & ~self.retired
        for arena in np.flatnonzero(fresh.any(axis=1)):
            self.sim.remove_agents(int(arena), np.flatnonzero(fresh[arena]))
        self.retired |= slots
        self.ended &= ~slots

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
            if (owned[arena] == mine).all():
                # Alone on this road: a real reset, seeded as asked.
                self.sim.reset([arena], seeds=[seed])
                self.sim.remove_agents(arena, np.flatnonzero(~mine))
            else:
                self.sim.respawn_agents(arena, np.flatnonzero(mine))
            self.ended[arena, mine] = False
            self.retired[arena, mine] = False
            self.last_reward[arena, mine] = 0.0
            self.last_applied[arena, mine] = -1
            self.last_terms[arena, mine] = 0.0
        member.pending = None
        if not any(m.pending is not None for m in self.members.values()):
            self.deadline = None
        return self.current_steps(trainer)

    def current_steps(self, trainer: str) -> Steps:
        """The trainer's agents as they are now (after a claim), reward 0, no flags."""
        flags = np.zeros(self.shape, dtype=bool)
        return self._steps(
            self.members[trainer].slots,
            self._arena_view(),
            np.zeros(self.shape),
            flags,
            flags,
            np.full(self.shape, -1, np.int64),
            flags,
            np.zeros(self.shape + (len(self.sim.reward_terms),)),
        )

    def _steps_for_members(
        self, reward, terminated, truncated, applied, late, terms
    ) -> dict[str, Steps]:
        view = self._arena_view()
        self.last_observations = view[0]
        return {
            trainer: self._steps(
                member.slots, view, reward, terminated, truncated, applied, late, terms
            )
            for trainer, member in self.members.items()
        }

    def _arena_view(self) -> tuple[dict[str, np.ndarray], np.ndarray, np.ndarray]:
        """What every member's Steps share, computed once per round: observations, action
        masks and the metrics table (A, N, fields)."""
        return self.sim.observe(), self.sim.action_mask(), self.sim.metrics_table()

    def _steps(
        self,
        slots: np.ndarray,
        view: tuple[dict[str, np.ndarray], np.ndarray, np.ndarray],
        reward,
        terminated,
        truncated,
        applied,
        late,
        terms,
    ) -> Steps:
        observations, action_mask, table = view
        arenas, n = self.shape
        total = arenas * n
        everyone = bool(slots.all())
        flat = np.arange(total, dtype=np.int32) if everyone else np.flatnonzero(slots)

        def rows(value: np.ndarray) -> np.ndarray:
            value = value.reshape((total,) + value.shape[2:])
            return value if everyone else value[flat]

        # Built from the simulation's own arrays, whose dtypes and shapes the spec fixes: the
        # per-field checks that guard decoding are skipped on this hot path (a test decodes
        # these messages and so checks them).
        return Steps.trusted(
            server=self.server,
            group=self.group_id,
            round=self.round,
            agents=flat.astype(np.int32),
            observations={name: rows(value) for name, value in observations.items()},
            reward=rows(reward),
            terminated=rows(terminated),
            truncated=rows(truncated),
            action_applied=rows(applied),
            late=rows(late),
            action_mask=rows(action_mask),
            reward_terms=rows(terms),
            metrics=rows(table),
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
        return self.last_observations or self.sim.observe()
