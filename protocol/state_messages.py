"""The messages that keep a group's whole state and put it back (protocol 1.8): what an exact
resume of a remote run asks of the server. Registered with the others in
:data:`~overtake.protocol.messages.MESSAGE_TYPES`."""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from .records import MAX_FRAME_BYTES, Message, check_name, check_range


@dataclass(frozen=True, eq=False)
class SnapshotRequest(Message):
    """Keep the group's whole state as it is between rounds (its arenas, their generators and
    what each slot carries to the next round); reply: :class:`GroupState`. For a trainer that
    owns every car of the group and has no actions waiting: the state it gets back is what
    :class:`RestoreRequest` puts back, for an exact resume (protocol 1.8)."""

    TYPE: ClassVar[str] = "snapshot"
    trainer: str  # the trainer's name
    ticket: bytes  # the ticket of the group's Opened
    group: int  # the group's id

    def check(self) -> None:
        check_name("trainer", self.trainer)


@dataclass(frozen=True, eq=False)
class GroupState(Message):
    """A group's whole state, in the server's own encoding: trainers keep it and hand it
    back (:class:`RestoreRequest`), they do not read it."""

    TYPE: ClassVar[str] = "group_state"
    group: int  # the group's id
    state: bytes  # opaque to trainers

    def check(self) -> None:
        check_range("state's bytes", len(self.state), 0, MAX_FRAME_BYTES)


@dataclass(frozen=True, eq=False)
class RestoreRequest(Message):
    """Put a group back as a :class:`GroupState` of the same configuration and size found it
    (of this group, or of one another server opened the same way); reply: :class:`Steps` of
    the trainer's agents now, reward 0, no flags, at the group's current round. The rounds
    after it are those that followed the snapshot, bit for bit. For a trainer that owns every
    car of the group and has no actions waiting (protocol 1.8)."""

    TYPE: ClassVar[str] = "restore"
    trainer: str  # the trainer's name
    ticket: bytes  # the ticket of the group's Opened
    group: int  # the group's id
    state: bytes  # a GroupState's state

    def check(self) -> None:
        check_name("trainer", self.trainer)
        check_range("state's bytes", len(self.state), 0, MAX_FRAME_BYTES)
