"""Rounds: the road stepped round after round, apart from who owns which car.

A round is one decision of every arena with Gymnasium's next-step autoreset
(:func:`~.sim.autoreset_round`): the episodes that ended last round restart, the others step.
Between rounds each agent slot carries whose episode ended, which cars were taken off the road
until their arena is reset, and what each slot got last round (reward, applied action, reward
terms: what world frames show): :data:`SLOT_ARRAYS`, what a
:class:`~.group_snapshot.GroupSnapshot` keeps.

Who owns which slot is not here. A server's :class:`~.groups.Group` holds a :class:`Rounds`
and the ledger of its trainers, and cuts each trainer's Steps from a round's
:class:`RoundRows` (the contract's :class:`~overtake.protocol.rows.Rows`); the in-process engine
(:class:`~.local.LocalEngine`) owns every car and plays a :class:`Rounds` directly, and its faces
read the rows: no trainer, no ticket, no message.
"""

from __future__ import annotations

import numpy as np

from overtake.protocol.rows import Rows

from ..sim import HighwaySim, autoreset_round

# The per-slot arrays a round leaves for the next (Rounds' attributes of these names).
SLOT_ARRAYS = ("ended", "retired", "last_reward", "last_applied", "last_terms")


# What a round gave agent slots: the contract's rows (a Steps carries the same, for a trainer's
# slots), in the simulator's dtypes.
RoundRows = Rows


class Rounds:
    """The rounds of one simulator's arenas, and what each agent slot carries between them."""

    def __init__(self, sim: HighwaySim) -> None:
        self.sim = sim
        shape = (sim.num_arenas, sim.agents)
        self.ended = np.zeros(shape, dtype=bool)  # whose episode ended last round
        self.retired = np.zeros(shape, dtype=bool)  # off the road until their arena is reset
        self.last_reward = np.zeros(shape)
        self.last_applied = np.full(shape, -1, dtype=np.int64)
        self.last_terms = np.zeros(shape + (len(sim.reward_terms),))
        self.round = 0  # rounds played
        self.last_observations: dict[str, np.ndarray] | None = None  # for spectators
        # Every round's rows share it: read-only, so that no reader can change another's.
        self._every_slot = np.arange(shape[0] * shape[1], dtype=np.int32)
        self._every_slot.setflags(write=False)

    @property
    def shape(self) -> tuple[int, int]:
        return self.sim.num_arenas, self.sim.agents

    def play(self, actions: np.ndarray, late: np.ndarray, owned: np.ndarray) -> RoundRows:
        """One round of (A, N) ``actions`` (``late``: the slots whose action did not come;
        ``owned``: the slots somebody drives); every slot's row, in slot order. A slot that
        restarts this round or whose car is off the road had no decision to miss: not late."""
        sim = self.sim
        if late.any():
            late = late & ~self.ended & ~self.retired
        result = autoreset_round(sim, actions, self.ended & owned, sim.agents_present())
        # Filled column by column: np.stack costs more than the copy on arrays this small.
        terms = np.empty(self.shape + (len(sim.reward_terms),))
        for i, name in enumerate(sim.reward_terms):
            terms[..., i] = result.reward_terms[name]
        self.ended = result.ended
        self.last_reward, self.last_applied, self.last_terms = (
            result.reward,
            result.action_applied,
            terms,
        )
        self.round += 1
        self.last_observations = self.sim.observe()
        return self._rows(
            self.last_observations,
            result.reward,
            result.terminated,
            result.truncated,
            result.action_applied,
            late,
            terms,
        )

    def now(self) -> RoundRows:
        """Every slot as it is now (after a reset or a claim): reward 0, no flags, action -1."""
        flags = np.zeros(self.shape, dtype=bool)
        return self._rows(
            self.sim.observe(),
            np.zeros(self.shape),
            flags,
            flags,
            np.full(self.shape, -1, np.int64),
            flags,
            np.zeros(self.shape + (len(self.sim.reward_terms),)),
        )

    def _rows(self, observations, reward, terminated, truncated, applied, late, terms) -> RoundRows:
        total = self._every_slot.size

        def rows(value: np.ndarray) -> np.ndarray:
            return value.reshape((total,) + value.shape[2:])

        sim = self.sim
        # Built from the simulation's own arrays, whose dtypes and shapes the spec fixes.
        return RoundRows(
            agents=self._every_slot,
            observations={name: rows(value) for name, value in observations.items()},
            reward=rows(reward),
            terminated=rows(terminated),
            truncated=rows(truncated),
            action_applied=rows(applied),
            late=rows(late),
            action_mask=rows(sim.action_mask()),
            reward_terms=rows(terms),
            metrics=rows(sim.metrics_table()),
        )

    def retire(self, agents: np.ndarray) -> None:
        """Take cars (slot ids) off the road before a round; they stay off, not restarted, until
        their arena is reset (a car that just ended is not restarted either)."""
        slots = np.zeros(self.shape, dtype=bool)
        slots.reshape(-1)[agents] = True
        fresh = slots & ~self.retired
        for arena in np.flatnonzero(fresh.any(axis=1)):
            self.sim.remove_agents(int(arena), np.flatnonzero(fresh[arena]))
        self.retired |= slots
        self.ended &= ~slots

    def clear(self, slots: np.ndarray) -> None:
        """Forget what the (A, N) ``slots`` carried: a new car, a reset or a car that left."""
        self.ended &= ~slots
        self.retired &= ~slots
        self.last_reward[slots] = 0.0
        self.last_applied[slots] = -1
        self.last_terms[slots] = 0.0

    def reset_arena(self, arena: int, seed: int | None, mine: np.ndarray, alone: bool) -> None:
        """Restart the episodes of slots ``mine`` (N,) of ``arena``: the whole road, seeded,
        where they are ``alone`` on it (the other slots' cars taken off), else only their cars,
        placed back on the road that goes on."""
        if alone:
            self.sim.reset([arena], seeds=[seed])
            self.sim.remove_agents(arena, np.flatnonzero(~mine))
        else:
            self.sim.respawn_agents(arena, np.flatnonzero(mine))
        slots = np.zeros(self.shape, dtype=bool)
        slots[arena] = mine
        self.clear(slots)

    def latest_observations(self) -> dict[str, np.ndarray]:
        """Every agent's observation of the last round (observed now before the first)."""
        return self.last_observations or self.sim.observe()
