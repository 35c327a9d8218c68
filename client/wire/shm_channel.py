"""The trainer's side of the shared-memory channel (protocol 1.7,
:mod:`overtake.ipc.shared_memory`): attach to the segment a server offers, write each
round's Actions into it and ring, sleep on the Steps bell, and read the round's Steps out.
What the server sends over Zenoh instead (an error) is counted in the segment's header, so
that a trainer asleep on the bell knows to look at its Zenoh inbox."""

from __future__ import annotations

import logging

import numpy as np

from overtake.ipc.doorbell import AVAILABLE as DOORBELL_AVAILABLE
from overtake.ipc.shared_memory import (
    ACTIONS_BELL_OFFSET,
    STEPS_BELL_OFFSET,
    Place,
    Segment,
)
from overtake.protocol import errors
from overtake.protocol.messages import Actions, ShmOffer, Steps
from overtake.protocol.rows import row_values

log = logging.getLogger("overtake.client")

_EMPTY = np.zeros(0, dtype=np.int32)


class ShmChannel:
    """An attached segment with its layout: Actions in, Steps out, a doorbell each way (a
    :class:`~overtake.client.wire.steps_channel.StepsChannel`)."""

    name = "shm"

    def __init__(self, segment: Segment, places: list[Place], server: str, group: int) -> None:
        self.segment, self.server, self.group = segment, server, group
        segment.lay_out(places)  # DecodeError where the layout does not fit the segment
        self._steps_names = [p[0] for p in places if not p[0].startswith("actions/")]
        self._steps_bell = segment.bell(STEPS_BELL_OFFSET)
        self._actions_bell = segment.bell(ACTIONS_BELL_OFFSET)
        self._bell_seen = self._steps_bell.value
        self.zenoh_seen = segment.zenoh_sent
        """messages the server sent over Zenoh for this group that this side has taken"""
        self._taken_round = -1
        self.rounds = 0
        """rounds whose Steps came through the segment"""
        self.closed = False

    def send_actions(self, actions: Actions) -> None:
        """Write a round's Actions into the segment and ring."""
        self.segment.write_actions(
            actions.round,
            actions.trainer_step,
            actions.agents,
            actions.actions,
            actions.retire if actions.retire is not None else _EMPTY,
        )
        self._actions_bell.ring()

    def take(self, round_: int) -> Steps | None:
        """Round ``round_``'s Steps if the segment holds them (once); None otherwise."""
        segment = self.segment
        if round_ == self._taken_round or segment.steps_round() != round_:
            return None
        if segment.generation % 2:
            # The server has put the round's number down and not yet finished the write (the
            # round comes before the closing generation): its bell rings when it has.
            return None
        written_round, arrays = segment.read_steps(self._steps_names)
        if written_round != round_:
            return None  # the server wrote on meanwhile (it does not in lock step)
        self._taken_round = round_
        self.rounds += 1
        return Steps(server=self.server, group=self.group, round=round_, **row_values(arrays))

    def zenoh_pending(self) -> bool:
        """Whether the server sent this group something over Zenoh that is not taken yet."""
        return self.segment.zenoh_sent != self.zenoh_seen

    def heard_over_zenoh(self) -> None:
        if self.zenoh_pending():
            self.zenoh_seen = (self.zenoh_seen + 1) & 0xFFFFFFFF

    def wait(self, timeout_s: float, spin_s: float = 0.0) -> bool:
        """Wait until the server rings (a round written or a message sent over Zenoh), a
        :meth:`wake`, or ``timeout_s``, spinning for the first ``spin_s`` of it
        (:meth:`overtake.ipc.doorbell.Bell.wait`); False at once where the server sent
        something over Zenoh that is not taken yet (it is in the connection's inbox)."""
        if self.zenoh_pending():
            return False
        self._bell_seen = self._steps_bell.wait(self._bell_seen, timeout_s, spin_s)
        return True

    def wake(self) -> None:
        """End a :meth:`wait` (the server's token went: the waiter looks at it)."""
        if not self.closed:
            self._steps_bell.wake()

    def close(self, unlink: bool) -> None:
        """Unmap (idempotent); ``unlink``: remove the name too (the server cannot any more)."""
        if self.closed:
            return
        self.closed = True
        if unlink:
            self.segment.unlink()
        self.segment.close()


def attach(server: str, group: int, offer: ShmOffer | None, required: bool) -> ShmChannel | None:
    """The offered segment, mapped and checked against its layout; None where it cannot be
    (the rounds then go over Zenoh). ``required`` (the trainer asked for ``shm``): a missing
    or unreachable segment is an error (:class:`~overtake.protocol.errors.ConnectError`) that
    says why."""
    why = None
    if offer is None:
        why = (
            "offered no shared memory (it runs with --no-shared-memory, speaks protocol 1.5 or "
            "older, or could not make a segment)"
        )
    elif not offer.layout:
        why = "offered a protocol 1.6 segment, without the doorbell this trainer reads"
    elif not DOORBELL_AVAILABLE:
        why = "cannot be reached here: this machine has no futex doorbell"
    if why is not None:
        if required:
            raise errors.ConnectError(f"transport shm: server {server} {why}")
        log.info("server %s %s: rounds over Zenoh", server, why)
        return None
    assert offer is not None
    places = [(a.name, a.offset, a.dtype, a.shape) for a in offer.layout]
    try:
        segment = Segment.attach(offer.name, offer.nonce, offer.size_bytes)
        try:
            return ShmChannel(segment, places, server, group)
        except errors.DecodeError:
            segment.close()
            raise
    except (OSError, errors.DecodeError) as error:
        if required:
            raise errors.ConnectError(
                f"transport shm: cannot attach server {server}'s segment {offer.name} ({error}); "
                "is the server on this host, sharing its /dev/shm (not another container)?"
            ) from None
        log.info(
            "server %s is not on this host's shared memory (%s): rounds over Zenoh", server, error
        )
        return None
