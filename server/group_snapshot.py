"""A group's rounds as they stand, to put back later: the simulator's snapshot and what each
agent slot carries from one round to the next.

Between rounds a :class:`~.groups.Group` holds, beside its simulator, whose episodes ended last
round (they restart next round: Gymnasium's next-step autoreset), which cars were retired, and
what each slot got last round (reward, applied action, reward terms: what world frames show).
:class:`GroupSnapshot` keeps all of it, so that a group restored from one plays the next rounds
exactly as the group it was taken from would have. Membership (who owns which slot, their
tickets) and the protocol's round counter are not in it: they belong to the connections of
now, not to the road.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from .sim.snapshot import SimSnapshot, SnapshotMismatch

if TYPE_CHECKING:
    from .groups import Group

# The per-slot arrays a round leaves for the next (Group's fields of these names).
SLOT_ARRAYS = ("ended", "retired", "last_reward", "last_applied", "last_terms")


@dataclass(frozen=True)
class GroupSnapshot:
    """A group's simulator and its per-slot round state (:data:`SLOT_ARRAYS`)."""

    sim: SimSnapshot
    slots: Mapping[str, np.ndarray]

    @classmethod
    def of(cls, group: Group) -> GroupSnapshot:
        return cls(
            sim=group.sim.snapshot(),
            slots={name: getattr(group, name).copy() for name in SLOT_ARRAYS},
        )

    def restore_into(self, group: Group) -> None:
        """Put ``group``'s road and rounds back as they were (checked first: a snapshot of
        another configuration or size changes nothing and raises
        :class:`~.sim.snapshot.SnapshotMismatch`)."""
        for name in SLOT_ARRAYS:
            want, have = getattr(group, name), self.slots.get(name)
            if have is None or have.shape != want.shape or have.dtype != want.dtype:
                found = "nothing" if have is None else f"{have.dtype}{have.shape}"
                raise SnapshotMismatch(
                    f"the snapshot's {name} is {found}, the group needs {want.dtype}{want.shape}"
                )
        group.sim.restore(self.sim)
        for name in SLOT_ARRAYS:
            getattr(group, name)[...] = self.slots[name]
        # Spectators are shown the restored road, observed afresh.
        group.last_observations = None

    def to_plain(self) -> dict[str, Any]:
        return {"sim": self.sim.to_plain(), "slots": dict(self.slots)}

    @classmethod
    def from_plain(cls, plain: Mapping[str, Any]) -> GroupSnapshot:
        try:
            sim, slots = plain["sim"], plain["slots"]
            return cls(
                sim=SimSnapshot.from_plain(sim),
                slots={name: np.asarray(slots[name]) for name in SLOT_ARRAYS},
            )
        except (KeyError, TypeError) as error:
            raise SnapshotMismatch(f"not a group snapshot ({error!r})") from None
