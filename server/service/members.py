"""A trainer's stake in a group (:class:`Member`): the agent slots it owns, its ticket, its
actions for the round, what it may send (:meth:`Member.check`), and its rows of a round as the
Steps sent to it (:meth:`Member.steps`). The group (:mod:`.groups`) keeps the ledger of its
members and plays the rounds; what is one member's alone is here."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from overtake.protocol import errors
from overtake.protocol.messages import Actions, Steps

from ..engine.rounds import RoundRows


@dataclass
class Member:
    """A trainer's stake in a group."""

    ticket: bytes
    slots: np.ndarray  # (A, N) bool: the agent slots it owns
    pending: Actions | None = None  # its actions for the current round
    count: int = 0  # how many slots it owns (slots.sum())

    def check(self, actions: Actions, group_id: int, round_: int) -> None:
        """Refuse Actions that answer another round than ``round_``, or name agents that are
        not this member's (to act or to retire), saying which."""
        if actions.round < round_:
            raise errors.StaleActions(
                f"actions answer round {actions.round}, but group {group_id} played it at the "
                f"deadline and is at round {round_}"
            )
        if actions.round > round_:
            raise errors.BadAction(
                f"actions answer round {actions.round}, but group {group_id} is only at round "
                f"{round_}"
            )
        self._check_own(actions.agents, group_id, actions.trainer, retiring=False)
        if actions.retire is not None and actions.retire.size:
            self._check_own(actions.retire, group_id, actions.trainer, retiring=True)

    def _check_own(
        self, agents: np.ndarray, group_id: int, trainer: str, *, retiring: bool
    ) -> None:
        """Refuse agent ids out of the group's range, or not this member's."""
        total = self.slots.size
        if agents.size and (agents.min() < 0 or agents.max() >= total):
            asked = "asked to retire " if retiring else "got "
            raise errors.BadAction(
                f"agent ids in group {group_id} are 0..{total - 1}, {asked}"
                f"{agents[(agents < 0) | (agents >= total)].tolist()}"
            )
        theirs = ~self.slots.reshape(-1)[agents]
        if theirs.any():
            may = "may retire only its own, " if retiring else "owns "
            raise errors.NotOwner(
                f"agents {agents[theirs].tolist()} of group {group_id} belong to another "
                f"trainer or to nobody; {trainer!r} {may}{np.flatnonzero(self.slots).tolist()}"
            )

    def steps(self, rows: RoundRows, server: str, group_id: int, round_: int) -> Steps:
        """This member's rows of a round, as the Steps sent to its trainer."""
        every = self.count == rows.agents.size
        values = rows.taken(None if every else np.flatnonzero(self.slots))
        # The slot ids are the message's own (the round's are shared by every member).
        values["agents"] = values["agents"].copy()
        # Built from the simulation's own arrays, whose dtypes and shapes the spec fixes: the
        # per-field checks that guard decoding are skipped on this hot path (a test decodes
        # these messages and so checks them).
        return Steps.trusted(server=server, group=group_id, round=round_, **values)
