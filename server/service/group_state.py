"""A group's whole state kept and put back for its one trainer (protocol 1.8's
SnapshotRequest and RestoreRequest): the engine's :class:`~..engine.group_snapshot.GroupSnapshot`
of a server's group, only for a trainer that owns every car of it, between rounds."""

from __future__ import annotations

from overtake.protocol import errors
from overtake.protocol.messages import GroupState, Steps

from ..engine.group_snapshot import GroupSnapshot
from ..sim.snapshot import SnapshotMismatch
from .groups import Group


def keep_state(group: Group, trainer: str, ticket: bytes) -> GroupState:
    """``group``'s whole state for ``trainer`` (alone in it, between rounds): SnapshotRequest."""
    _alone_between_rounds(group, trainer, ticket, "keep")
    return GroupState(group=group.group_id, state=GroupSnapshot.of(group.rounds).to_bytes())


def restore_state(group: Group, trainer: str, ticket: bytes, state: bytes) -> Steps:
    """Put back a state :func:`keep_state` gave (of a group of the same configuration and
    size): RestoreRequest; returns ``trainer``'s Steps now."""
    _alone_between_rounds(group, trainer, ticket, "restore")
    try:
        GroupSnapshot.from_bytes(state).restore_into(group.rounds)
    except SnapshotMismatch as error:
        raise errors.BadConfig(f"group {group.group_id} cannot take this state: {error}") from None
    return group.current_steps(trainer)


def _alone_between_rounds(group: Group, trainer: str, ticket: bytes, verb: str) -> None:
    member = group.member(trainer, ticket)
    if len(group.members) > 1 or not member.slots.all():
        raise errors.NotOwner(
            f"only a trainer that owns every car of group {group.group_id} may {verb} its "
            f"state; {trainer!r} owns {member.count} of {member.slots.size} and "
            f"{len(group.members) - 1} other trainer(s) are in it"
        )
    if member.pending is not None:
        raise errors.BadAction(
            f"group {group.group_id}: {trainer!r}'s actions for round {group.round} are "
            f"waiting; {verb} its state between rounds (receive the round's Steps first)"
        )
