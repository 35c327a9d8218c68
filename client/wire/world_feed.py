"""Read-only spectators: every vehicle of every arena, at the server's world rate.

A spectator subscribes to the servers' world topics and keeps only the latest frame of each
arena; the servers publish those frames with dropping congestion control and only while
somebody watches, so a slow spectator costs the simulation nothing and never holds it back.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque

import zenoh

from overtake.client.wire.remote_config import RemoteConfig, unreachable_message
from overtake.ipc.transport import on_zenoh_thread, open_session
from overtake.protocol import codec, errors, keys
from overtake.protocol.messages import WorldFrame

log = logging.getLogger("overtake.client.wire.world_feed")


class Spectator:
    """Watch ``server``'s arenas (every server's by default; one ``arena`` if given)."""

    def __init__(
        self,
        config: RemoteConfig,
        server: str | None = None,
        arena: int | None = None,
        backlog: int = 64,
    ) -> None:
        if arena is not None and server is None:
            raise ValueError("watching one arena needs its server's name")
        try:
            self.session = open_session(config.session_config())
        except zenoh.ZError as error:
            raise errors.ConnectError(unreachable_message(config, error)) from None
        key = keys.world_all() if server is None else keys.world(server, arena)
        self._latest: dict[tuple[str, int], WorldFrame] = {}
        self._recent: deque[WorldFrame] = deque(maxlen=backlog)  # oldest dropped first
        self._changed = threading.Condition()
        self.frames_received = 0
        self.frames_refused = 0
        self._subscriber = self.session.declare_subscriber(key, on_zenoh_thread(self._on_sample))

    def _on_sample(self, sample: zenoh.Sample) -> None:
        try:
            frame = codec.decode(sample.payload.to_bytes(), WorldFrame)
            if not isinstance(frame, WorldFrame):
                raise errors.DecodeError(f"expected a world frame, got {frame.TYPE}")
        except errors.ProtocolError as error:
            self.frames_refused += 1
            log.warning("refused a world frame on %s: %s", sample.key_expr, error)
            return
        with self._changed:
            self._latest[(frame.server, frame.arena)] = frame
            self._recent.append(frame)
            self.frames_received += 1
            self._changed.notify_all()

    def latest(self) -> dict[tuple[str, int], WorldFrame]:
        """The newest frame of every (server, arena) seen so far."""
        with self._changed:
            return dict(self._latest)

    def next_frame(self, timeout_s: float) -> WorldFrame | None:
        """The oldest frame not yet taken (older ones beyond the backlog were dropped)."""
        deadline = time.monotonic() + timeout_s
        with self._changed:
            while not self._recent:
                remaining = deadline - time.monotonic()
                if (remaining <= 0 or not self._changed.wait(remaining)) and not self._recent:
                    return None
            return self._recent.popleft()

    def close(self) -> None:
        try:
            self._subscriber.undeclare()
        finally:
            self.session.close()

    def __enter__(self) -> Spectator:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
