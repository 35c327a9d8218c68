"""The server's inbox: what arrives from Zenoh, queued for the server's one loop.

Zenoh's threads only enqueue (small records, decoded and checked by the loop alone), within
bounds a flood cannot pass: actions waiting per key and requests waiting in all. A request
beyond the bound is answered busy at once from a prepared frame, actions beyond it are
dropped; both are counted, and the loop warns about them at most every few seconds.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
import time
from dataclasses import dataclass

import zenoh

from overtake.protocol import codec, errors, keys
from overtake.protocol.messages import ErrorReply

log = logging.getLogger("overtake.server")


@dataclass(frozen=True)
class QueryArrived:
    query: zenoh.Query
    payload: bytes


@dataclass(frozen=True)
class ActionsArrived:
    key: str
    payload: bytes


@dataclass(frozen=True)
class ActionsRung:
    """A trainer wrote its Actions into its segment and rang (protocol 1.7's shared-memory
    channel); the loop reads them from the segment."""

    trainer: str
    group: int

    @property
    def key(self) -> str:
        """Its queue's key: one per segment, bounded as a Zenoh key's actions are."""
        return f"shm/{self.trainer}/{self.group}"


@dataclass(frozen=True)
class TrainerPresence:
    """A trainer's liveliness token appeared (``present``) or went away."""

    key: str
    present: bool


@dataclass(frozen=True)
class Wake:
    """Nothing to do but look at the clock (a stop request, or a deadline)."""


Event = QueryArrived | ActionsArrived | ActionsRung | TrainerPresence | Wake
WAKE = Wake()
# Events handled before the ready groups step: bounds what a flood of messages can delay.
MAX_EVENTS_PER_PASS = 256
# What a flood may queue before the loop reads it (bench/fuzz/fuzz_wire.py: a million unreadable
# actions on one key queued 150 MiB). Actions waiting per key (per trainer name): a trainer in
# lock step has one at a time, so only a flood on its key reaches the bound. Requests waiting
# in all (their sender is not known before decoding): beyond it a request is answered busy.
MAX_QUEUED_ACTIONS_PER_KEY = 64
MAX_QUEUED_REQUESTS = 1024
# At most one warning about dropped frames per this many seconds.
DROPPED_REPORT_INTERVAL_S = 5.0


def busy_reply(server: str) -> ErrorReply:
    """The answer to a request that finds MAX_QUEUED_REQUESTS already waiting."""
    return ErrorReply(
        code=errors.ServerBusy.code,
        message=f"server {server} is busy: {MAX_QUEUED_REQUESTS} requests are waiting "
        "already, so this one was not queued; ask again",
    )


@dataclass(frozen=True)
class Backlog:
    """What waits in the inbox, and what a flood lost at its bounds since the start."""

    queued_actions: int
    queued_requests: int
    dropped_frames: int


class Inbox:
    """The queue between Zenoh's threads (the ``on_*`` callbacks) and the server's loop."""

    def __init__(self, server: str) -> None:
        self.server = server
        self._events: queue.SimpleQueue[Event] = queue.SimpleQueue()
        # Frames queued and not yet handled, counted by Zenoh's threads and the loop alike.
        self._lock = threading.Lock()
        self._queued_actions: dict[str, int] = {}
        self._queued_requests = 0
        self._dropped = 0
        self._dropped_reported = 0
        self._dropped_report_t = 0.0
        self._busy_frame = codec.encode(busy_reply(server))

    # Zenoh's threads ---------------------------------------------------------------------

    def on_query(self, query: zenoh.Query) -> None:
        """Queue a request, unless a flood already filled the queue; then it is answered busy
        at once (a prepared frame: no decoding, nothing kept), so that an honest asker caught
        in the flood hears why and asks again instead of timing out."""
        with self._lock:
            full = self._queued_requests >= MAX_QUEUED_REQUESTS
            if full:
                self._dropped += 1
            else:
                self._queued_requests += 1
        if full:
            with contextlib.suppress(Exception), query:
                query.reply(keys.server_request(self.server), self._busy_frame)
            return
        self._events.put(QueryArrived(query, query.payload.to_bytes() if query.payload else b""))

    def on_actions(self, sample: zenoh.Sample) -> None:
        """Queue actions, unless their key already has its share queued."""
        key = str(sample.key_expr)
        if self._count_actions(key):
            self._events.put(ActionsArrived(key, sample.payload.to_bytes()))

    def on_ring(self, trainer: str, group: int) -> None:
        """Queue a ring of a segment's Actions bell (from the channel's thread), unless its
        share is queued already (a trainer ringing without waiting for its Steps)."""
        event = ActionsRung(trainer, group)
        if self._count_actions(event.key):
            self._events.put(event)

    def _count_actions(self, key: str) -> bool:
        """Count one more actions event queued on ``key``; False (dropped, counted) where
        its share is queued already."""
        with self._lock:
            waiting = self._queued_actions.get(key, 0)
            if waiting >= MAX_QUEUED_ACTIONS_PER_KEY:
                self._dropped += 1
                return False
            self._queued_actions[key] = waiting + 1
        return True

    def on_presence(self, sample: zenoh.Sample) -> None:
        self._events.put(TrainerPresence(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT))

    def wake(self) -> None:
        """Wake the loop (it looks at the clock and its stop flag)."""
        self._events.put(WAKE)

    # The loop ------------------------------------------------------------------------------

    def take(self, timeout_s: float | None = 0.0) -> Event | None:
        """The next event, waiting up to ``timeout_s`` (0: not at all; None: for ever); None
        where nothing came. What it returns no longer counts against its queue's bound."""
        try:
            if timeout_s == 0:
                event = self._events.get_nowait()
            else:
                event = self._events.get(timeout=timeout_s)
        except queue.Empty:
            return None
        self._taken(event)
        return event

    def empty(self) -> bool:
        """Whether nothing waits (without waiting)."""
        return self._events.empty()

    def backlog(self) -> Backlog:
        with self._lock:
            return Backlog(
                queued_actions=sum(self._queued_actions.values()),
                queued_requests=self._queued_requests,
                dropped_frames=self._dropped,
            )

    def _taken(self, event: Event) -> None:
        with self._lock:
            if isinstance(event, QueryArrived):
                self._queued_requests -= 1
            elif isinstance(event, (ActionsArrived, ActionsRung)):
                left = self._queued_actions[event.key] - 1
                if left:
                    self._queued_actions[event.key] = left
                else:
                    del self._queued_actions[event.key]
            dropped = self._dropped
        now = time.monotonic()
        if dropped > self._dropped_reported and now - self._dropped_report_t >= (
            DROPPED_REPORT_INTERVAL_S
        ):
            log.warning(
                "dropped %d frame(s) of a flood (%d in all): more than %d actions waiting on "
                "one key, or %d requests waiting",
                dropped - self._dropped_reported,
                dropped,
                MAX_QUEUED_ACTIONS_PER_KEY,
                MAX_QUEUED_REQUESTS,
            )
            self._dropped_reported, self._dropped_report_t = dropped, now
