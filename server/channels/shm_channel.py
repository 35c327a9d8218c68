"""Rounds through shared memory (protocol 1.7, :mod:`overtake.ipc.shared_memory`): for a
trainer on this host that holds its group alone, the server writes each round's Steps into a
segment and rings the Steps bell; the trainer writes its Actions there and rings the Actions
bell. The service loop, while it runs, looks at the bell itself (:meth:`ShmChannel.rung`); while
it sleeps on its inbox, a thread of this channel sleeps on the bell and turns a ring into an
inbox event (:meth:`ShmChannel.hear_rings`).
No round crosses Zenoh; what is not a round (an error) does, counted in the segment's header
and rung, so that the trainer looks for it.

A shared group steps on a deadline, which could overwrite a round a member is still reading,
so only a group's sole member is offered a channel.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

from overtake.ipc.doorbell import AVAILABLE as DOORBELL_AVAILABLE
from overtake.ipc.shared_memory import (
    ACTIONS_BELL_OFFSET,
    STEPS_BELL_OFFSET,
    Place,
    Segment,
    channel_plan,
)
from overtake.protocol.messages import Actions, Message, ShmArray, ShmOffer, Steps

from . import ChannelTerms, StepsChannel

log = logging.getLogger(__name__)

# The bell thread looks at its stop flag at least this often (a close also wakes it at once),
# whether it waits for the loop to sleep or for a ring.
BELL_SLICE_S = 0.5


class ShmChannel:
    """One member's segment, its layout, and the thread that hears its Actions bell.

    ``on_ring(trainer, group)`` is called on that thread when the trainer rings (it should
    only enqueue); the loop then takes the Actions with :meth:`actions`."""

    def __init__(
        self,
        segment: Segment,
        places: list[Place],
        trainer: str,
        group: int,
        ticket: bytes,
        fallback: StepsChannel,
        on_ring: Callable[[str, int], None],
    ) -> None:
        self.segment, self.trainer, self.group, self.ticket = segment, trainer, group, ticket
        self._fallback = fallback
        self._places = places
        segment.lay_out(places)
        self.reads = False
        """whether the trainer reads the segment: its first Actions came through it (Actions
        over Zenoh close the channel instead: Outbox.actions_over_zenoh)"""
        self.handled = 0
        """the Actions bell's value when the loop last took the Actions"""
        self._steps_bell = segment.bell(STEPS_BELL_OFFSET)
        self._actions_bell = segment.bell(ACTIONS_BELL_OFFSET)
        self._closed = threading.Event()
        self._on_ring = on_ring
        self._hearing = threading.Event()  # hear_rings
        self._thread = threading.Thread(
            target=self._listen, name=f"overtake-bell-{group}", daemon=True
        )
        self._thread.start()

    @classmethod
    def create(cls, terms: ChannelTerms) -> ShmChannel:
        """A channel for ``terms``' member, sized for its Steps as they are; OSError where
        no segment can be made."""
        current = terms.current
        places, size = channel_plan(current.agents.size, current.arrays())
        segment = Segment.create(size)
        try:
            return cls(
                segment,
                places,
                terms.trainer,
                current.group,
                terms.ticket,
                terms.fallback,
                terms.on_ring,
            )
        except BaseException:
            segment.unlink()
            segment.close()
            raise

    def offer(self) -> ShmOffer:
        return ShmOffer(
            name=self.segment.name,
            nonce=self.segment.nonce,
            size_bytes=self.segment.size,
            layout=tuple(
                ShmArray.trusted(name=n, offset=o, dtype=d, shape=s) for n, o, d, s in self._places
            ),
        )

    def _listen(self) -> None:
        """Turn the trainer's rings into ``on_ring`` calls while the service loop sleeps; while
        it runs, stay off the bell (a ring then wakes nobody: the loop looks at :meth:`rung`)."""
        bell = self._actions_bell
        told = None  # the ring last turned into an event
        while not self._closed.is_set():
            if not self._hearing.wait(BELL_SLICE_S):
                continue
            value = bell.value
            if value != self.handled and value != told and not self._closed.is_set():
                told = value  # rung since the loop took the Actions: it must hear of it
                self._on_ring(self.trainer, self.group)
                continue
            bell.wait(value, BELL_SLICE_S)

    def hear_rings(self, on: bool) -> None:
        if on:
            self._hearing.set()
        else:
            self._hearing.clear()

    def rung(self) -> bool:
        """Whether the trainer rang since the loop last took its Actions."""
        return not self._closed.is_set() and self._actions_bell.value != self.handled

    def actions(self) -> Actions:
        """The Actions the trainer wrote, checked as a decoded frame is
        (:class:`~overtake.protocol.errors.DecodeError` where they are malformed)."""
        self.handled = self._actions_bell.value
        round_, trainer_step, agents, actions, retire = self.segment.read_actions()
        if not self.reads:
            # The name was only for finding the segment: once the trainer reads it, it goes,
            # so nothing is left in /dev/shm however either side ends, SIGKILL included.
            self.reads = True
            self.segment.unlink()
        return Actions(
            trainer=self.trainer,
            ticket=self.ticket,
            group=self.group,
            round=round_,
            agents=agents,
            actions=actions,
            trainer_step=trainer_step,
            retire=retire if retire.size else None,
        )

    def send_steps(self, steps: Steps) -> None:
        if self.reads and self.segment.write_steps(steps.round, steps.arrays()):
            self._steps_bell.ring()
            return
        self.send(steps)  # the trainer has not said it reads, or the round does not fit

    def send(self, message: Message) -> None:
        self._fallback.send(message)
        if not self._closed.is_set():
            self.segment.count_zenoh_sent()
            self._steps_bell.ring()

    def close(self) -> None:
        """Stop the bell thread, then remove and unmap the segment (idempotent)."""
        if self._closed.is_set():
            return
        self._closed.set()
        self._hearing.set()  # the thread may wait for the loop to sleep: it looks now
        self._actions_bell.wake()
        self._thread.join()
        self.segment.unlink()
        self.segment.close()


def make(terms: ChannelTerms) -> ShmChannel | None:
    """A segment for ``terms``' member, sized for its current Steps; None where this machine
    has no futex doorbell (said in the log)."""
    if not DOORBELL_AVAILABLE:
        log.info("no futex doorbell on this machine: %s's Steps go over Zenoh", terms.trainer)
        return None
    return ShmChannel.create(terms)
