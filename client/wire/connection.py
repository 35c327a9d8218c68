"""The trainer's Zenoh connection: one session with this trainer's liveliness token (a server
frees our arenas when it disappears), the subscriber our Steps arrive on, requests answered
with retries where a server is busy, and the servers on the network (their status, which one
takes a request)."""

from __future__ import annotations

import contextlib
import logging
import math
import os
import queue
import secrets
import socket
import threading
import time
from collections import deque
from typing import Any, TypeVar

import zenoh

from overtake.client.wire.remote_config import RemoteConfig, likely_causes, unreachable_message
from overtake.client.wire.steps_channel import StepsChannel, open_channel
from overtake.client.wire.stopping import INTERRUPT_AFTER_S, stop_event
from overtake.client.wire.zenoh_channel import ZenohChannel
from overtake.ipc.transport import on_zenoh_thread, open_session
from overtake.protocol import codec, errors, keys
from overtake.protocol.channel_offers import ChannelOffer
from overtake.protocol.messages import (
    Actions,
    ErrorReply,
    Message,
    StatusReply,
    StatusRequest,
    Steps,
)

log = logging.getLogger("overtake.client")
M = TypeVar("M", bound=Message)

# Messages dropped (unreadable, or not for us) are logged at most once per this many seconds.
DROPPED_LOG_INTERVAL_S = 5.0
# A request a busy server did not queue is asked again after this pause, doubled each time
# up to the maximum (a flood of requests usually drains within a second: bench/fuzz/fuzz_wire.py).
BUSY_FIRST_PAUSE_S = 0.05
BUSY_MAX_PAUSE_S = 1.0


def _trainer_id(prefix: str | None) -> str:
    host = "".join(c if c.isalnum() or c in "-_." else "-" for c in socket.gethostname())[:24]
    head = "".join(c if c.isalnum() or c in "-_." else "-" for c in (prefix or "trainer"))
    head = head[: keys.TRAINER_PREFIX_CHARS]
    return f"{head}-{host or 'host'}-{os.getpid()}-{secrets.token_hex(3)}"


class Connection:
    """One Zenoh session of one trainer."""

    def __init__(self, config: RemoteConfig) -> None:
        self.config = config
        self.trainer = _trainer_id(config.trainer_name or config.security.user_name())
        try:
            self.session = open_session(config.session_config())
        except zenoh.ZError as error:
            raise errors.ConnectError(unreachable_message(config, error)) from None
        self._inbox: queue.SimpleQueue[tuple[str, bytes]] = queue.SimpleQueue()
        self.interrupted = stop_event()  # set by interrupt_waits: long waits end
        self._buffered: dict[tuple[str, int], deque[Steps]] = {}
        self._errors: dict[tuple[str, int], deque[errors.ProtocolError]] = {}
        # The (server, group) pairs this connection steps: anything else that arrives is
        # stale or foreign and is dropped.
        self._stepping: set[tuple[str, int]] = set()
        # Each group's channel (steps_channel): how its Actions go and its rounds come.
        self._channels: dict[tuple[str, int], StepsChannel] = {}
        # Rounds delivered by channels since closed, by transport name.
        self._rounds_closed: dict[str, int] = {}
        self._servers_lost: set[str] = set()
        # Times each server's token disappeared: a group opened at one count is gone at the
        # next, even if a restarted server of the same name is back by the time we look.
        self._server_epoch: dict[str, int] = {}
        self._lock = threading.Lock()
        self._server_appeared = threading.Event()
        self._token = self.session.liveliness().declare_token(keys.trainer_alive(self.trainer))
        self._subscriber = self.session.declare_subscriber(
            keys.trainer_steps_all(self.trainer),
            on_zenoh_thread(self._on_steps),
        )
        self._alive_sub = self.session.liveliness().declare_subscriber(
            keys.ALL_SERVERS_ALIVE, on_zenoh_thread(self._on_server_alive), history=True
        )
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._drop_logged_t, self._drops_unlogged = -math.inf, 0
        self.dropped = 0
        """messages dropped in all (unreadable, not for us, or forged in our name)"""
        self.closed = False

    def _on_steps(self, sample: zenoh.Sample) -> None:
        self._inbox.put((str(sample.key_expr), sample.payload.to_bytes()))

    def _on_server_alive(self, sample: zenoh.Sample) -> None:
        try:
            server = keys.parse_server_alive(str(sample.key_expr))
        except errors.ProtocolError:
            return
        with self._lock:
            if sample.kind == zenoh.SampleKind.PUT:
                self._servers_lost.discard(server)
                self._server_appeared.set()
            else:
                self._servers_lost.add(server)
                self._server_epoch[server] = self._server_epoch.get(server, 0) + 1
        self._inbox.put(("", b""))  # wake a waiter
        for channel in tuple(self._channels.values()):
            channel.wake()  # a waiter asleep on its channel looks at the server too

    def server_lost(self, server: str) -> bool:
        with self._lock:
            return server in self._servers_lost

    def epoch(self, server: str) -> int:
        """How many times ``server`` has gone away since this connection opened."""
        with self._lock:
            return self._server_epoch.get(server, 0)

    # --- requests --------------------------------------------------------------------------

    def request(self, server: str, message: Message, expect: type[M]) -> M:
        """Send a request to one server; its reply, or the error it names. A server too busy
        to queue it (a flood) is asked again, waiting longer each time, until the request
        timeout; a busy server did not queue the request, so asking again is safe."""
        give_up = time.monotonic() + self.config.request_timeout_s
        pause_s = BUSY_FIRST_PAUSE_S
        while True:
            try:
                return self._request_once(server, message, expect)
            except errors.ServerBusy:
                if time.monotonic() + pause_s > give_up:
                    raise
                log.info("server %s is busy; asking again in %.2f s", server, pause_s)
                time.sleep(pause_s)
                pause_s = min(pause_s * 2, BUSY_MAX_PAUSE_S)

    def _request_once(self, server: str, message: Message, expect: type[M]) -> M:
        replies = list(
            self.session.get(
                keys.server_request(server),
                payload=codec.encode(message),
                timeout=self.config.request_timeout_s,
                target=zenoh.QueryTarget.ALL,
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
        )
        for reply in replies:
            if reply.ok is None:
                err = reply.err
                text = (
                    "no reply" if err is None else err.payload.to_bytes().decode("utf-8", "replace")
                )
                if self.server_lost(server):
                    raise errors.ServerLost(
                        f"server {server} went away during a {message.TYPE} request"
                    )
                raise errors.StepTimeout(
                    f"server {server} did not answer a {message.TYPE} "
                    f"request within {self.config.request_timeout_s:g} s "
                    f"({text})"
                )
            answer = codec.decode(reply.ok.payload.to_bytes(), expect)
            if isinstance(answer, ErrorReply):
                raise errors.error_from_code(answer.code, f"server {server}: {answer.message}")
            return answer
        raise errors.ServerLost(
            f"no server named {server!r} answers on {', '.join(self.config.connect)}"
        )

    def discover(self) -> list[StatusReply]:
        """Status of every server that answers within the request timeout."""
        replies = self.session.get(
            keys.ALL_SERVER_REQUESTS,
            payload=codec.encode(StatusRequest()),
            timeout=self.config.request_timeout_s,
            target=zenoh.QueryTarget.ALL,
        )
        found: list[StatusReply] = []
        mismatch: errors.VersionMismatch | None = None
        for reply in replies:
            if reply.ok is None:
                continue
            try:
                status = codec.decode(reply.ok.payload.to_bytes(), StatusReply)
            except errors.VersionMismatch as error:
                mismatch = error  # one old server must not hide the others
                log.warning("ignored a server of another protocol version: %s", error)
                continue
            except errors.ProtocolError as error:
                log.warning("ignored a bad status reply: %s", error)
                continue
            if isinstance(status, StatusReply):
                found.append(status)
        if not found and mismatch is not None:
            raise mismatch
        return found

    def candidates(self, arenas: int) -> list[str]:
        """Servers to ask, best first, by the rule in this module's docstring."""
        if self.config.server is not None:
            return [self.config.server]
        # A trainer may start together with its server (docker compose): keep asking for a
        # while before concluding that nobody is there.
        give_up = time.monotonic() + self.config.connect_timeout_s
        statuses = self.discover()
        while not statuses and time.monotonic() < give_up:
            # Woken when a server's liveliness token appears; its queryable is declared just
            # before the token, so it answers from then on.
            self._server_appeared.wait(timeout=max(give_up - time.monotonic(), 0.0))
            self._server_appeared.clear()
            statuses = self.discover()
        if not statuses:
            raise errors.ConnectError(
                f"connected to {', '.join(self.config.connect)}, but no overtake server "
                f"answered within {self.config.connect_timeout_s:g} s. "
                + likely_causes(self.config)
            )
        roomy = [s for s in statuses if s.arenas_free >= arenas]
        if not roomy:
            listing = ", ".join(f"{s.server} ({s.arenas_free} free)" for s in statuses)
            raise errors.ServerFull(f"no server has {arenas} free arena(s): {listing}")
        # Ties broken at random: trainers started together see the same statuses, and a tie
        # broken by name sent them all to the same server.
        tie_break = {s.server: secrets.randbits(32) for s in roomy}
        roomy.sort(key=lambda s: (-s.arenas_free, len(s.groups), tie_break[s.server]))
        return [s.server for s in roomy]

    # --- steps ----------------------------------------------------------------------------

    def rounds_through(self, transport: str) -> int:
        """Rounds whose Steps a ``transport`` channel delivered itself (the rest came through
        the Zenoh inbox)."""
        open_ = sum(c.rounds for c in self._channels.values() if c.name == transport)
        return self._rounds_closed.get(transport, 0) + open_

    def send_actions(self, server: str, actions: Actions) -> None:
        """A round's Actions, through the group's channel."""
        self._channel(server, actions.group).send_actions(actions)

    def _channel(self, server: str, group: int) -> StepsChannel:
        channel = self._channels.get((server, group))
        if channel is None:
            # A group stepped without a channel opened for it (joined, or an Actions for a
            # group being forgotten): over Zenoh, which reaches any server.
            channel = self._channels[(server, group)] = self._over_zenoh(server)
        return channel

    def _over_zenoh(self, server: str) -> ZenohChannel:
        pub = self._publishers.get(server)
        if pub is None:
            pub = self._publishers[server] = self.session.declare_publisher(
                keys.server_actions(server, self.trainer),
                congestion_control=zenoh.CongestionControl.BLOCK,
                priority=zenoh.Priority.DATA_HIGH,
            )
        return ZenohChannel(pub)

    def _take(self, server: str, group: int, round_: int) -> Steps | None:
        """Round ``round_`` of ``group`` if it has arrived; older rounds are dropped."""
        arrived = self._buffered.setdefault((server, group), deque())
        while arrived:
            steps = arrived[0]
            if steps.round > round_:
                return None  # a later round is all there is: the caller is behind
            arrived.popleft()
            if steps.round == round_:
                return steps
            log.debug("dropped stale steps of group %d round %d", group, steps.round)
        failures = self._errors.get((server, group))
        if failures:
            raise failures.popleft()
        return None

    def arrived(self, server: str, group: int, round_: int) -> Steps | None:
        """Without waiting: round ``round_`` of ``group`` if it is already here."""
        while True:
            try:
                key, payload = self._inbox.get_nowait()
            except queue.Empty:
                break
            if key:
                self._file(key, payload)
        steps = self._take(server, group, round_)
        if steps is None:
            steps = self._channel(server, group).take(round_)
        return steps

    def next_steps(self, server: str, group: int, round_: int, epoch: int) -> Steps:
        """Block until the :class:`Steps` of ``group``'s ``round_`` arrive: over Zenoh, or
        through the group's channel (asleep on what it waits on, a segment's bell)."""
        channel = self._channel(server, group)
        started = time.monotonic()
        deadline = started + self.config.step_timeout_s
        while True:
            steps = self._take(server, group, round_)
            if steps is None:
                steps = channel.take(round_)
            if steps is not None:
                return steps
            later = self._buffered.get((server, group))
            if later:
                # Rounds come in order: a later one without ours means ours will never come.
                raise errors.DecodeError(
                    f"expected round {round_} of group {group} from "
                    f"server {server}, got round {later[0].round}"
                )
            if self.server_lost(server) or self.epoch(server) != epoch:
                raise errors.ServerLost(
                    f"server {server} went away while we waited for round {round_} of group {group}"
                )
            if self.interrupted.is_set() and time.monotonic() - started > INTERRUPT_AFTER_S:
                raise errors.Interrupted(
                    f"asked to stop while waiting for round {round_} of group {group} from "
                    f"server {server}"
                )
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise errors.StepTimeout(
                    f"no observations from server {server} for round {round_} of group {group} "
                    f"within {self.config.step_timeout_s:g} s (the server's step deadline may "
                    "be longer; see RemoteConfig.step_timeout_s)"
                )
            if self._inbox.empty() and channel.wait(min(remaining, 0.5), self.config.spin_s):
                continue  # the channel waited on its own (nothing for us on Zenoh)
            try:
                key, payload = self._inbox.get(timeout=min(remaining, 0.5))
            except queue.Empty:
                continue
            if key:
                self._file(key, payload)
                channel.heard_over_zenoh()

    def _file(self, key: str, payload: bytes) -> None:
        sender = key.rsplit("/", 1)[-1]
        try:
            message = codec.decode(payload, Steps)
        except errors.ProtocolError as error:
            self._drop("dropped an unreadable message from server %s: %s", sender, error)
            return
        if isinstance(message, ErrorReply):
            if message.group is None or (sender, message.group) not in self._stepping:
                # Not about a group we step (perhaps garbage sent in our name): say so only.
                self._drop("server %s refused a message in our name: %s", sender, message.message)
                return
            self._errors.setdefault((sender, message.group), deque()).append(
                errors.error_from_code(message.code, f"server {sender}: {message.message}")
            )
            return
        assert isinstance(message, Steps)
        if message.server != sender or (sender, message.group) not in self._stepping:
            self._drop(
                "dropped steps of group %d from %s on server %s's key",
                message.group,
                message.server,
                sender,
            )
            return
        self._buffered.setdefault((sender, message.group), deque()).append(message)

    def _drop(self, message: str, *args: Any) -> None:
        """Log a message this connection dropped, at most once per DROPPED_LOG_INTERVAL_S,
        with how many went unlogged meanwhile: a flood of garbage in our name (bench/fuzz/fuzz_wire)
        would otherwise write a line per frame."""
        self.dropped += 1
        now = time.monotonic()
        if now - self._drop_logged_t < DROPPED_LOG_INTERVAL_S:
            self._drops_unlogged += 1
            return
        if self._drops_unlogged:
            message += " (and %d more dropped unlogged in the last %.0f s)"
            args += (self._drops_unlogged, now - self._drop_logged_t)
        log.warning(message, *args)
        self._drop_logged_t, self._drops_unlogged = now, 0

    def track(self, server: str, group: int) -> None:
        """Start accepting Steps and errors for ``group`` (after opening or joining it, or
        again after a reset: what arrived before is stale). Its channel, if any, stays."""
        self._buffered.pop((server, group), None)
        self._errors.pop((server, group), None)
        self._stepping.add((server, group))

    def open_channel(self, server: str, group: int, offer: ChannelOffer | None) -> str:
        """Open ``group``'s channel from what ``server`` offered in its reply
        (:func:`~overtake.client.wire.steps_channel.open_channel`, by
        :attr:`RemoteConfig.transport`); the transport's name."""
        channel = open_channel(
            server, group, offer, self.config.transport, lambda: self._over_zenoh(server)
        )
        self.attach(server, group, channel)
        return channel.name

    def attach(self, server: str, group: int, channel: StepsChannel) -> None:
        """Step ``group`` through ``channel`` from now on (a transport's channel, opened by
        :meth:`open_channel` or by a transport of the caller's own); the one it had is closed."""
        self._close_channel(server, group)
        self._channels[(server, group)] = channel

    def _close_channel(self, server: str, group: int) -> None:
        channel = self._channels.pop((server, group), None)
        if channel is not None:
            self._rounds_closed[channel.name] = (
                self._rounds_closed.get(channel.name, 0) + channel.rounds
            )
            channel.close(unlink=self.server_lost(server))  # its server cannot any more

    def forget(self, server: str, group: int) -> None:
        self._close_channel(server, group)
        self._stepping.discard((server, group))
        self._buffered.pop((server, group), None)
        self._errors.pop((server, group), None)

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        for server, group in list(self._channels):
            self._close_channel(server, group)
        # What went with the session already needs no undeclaring.
        declared: tuple[Any, ...] = (
            *self._publishers.values(),
            self._subscriber,
            self._alive_sub,
            self._token,
        )
        for obj in declared:
            with contextlib.suppress(Exception):
                obj.undeclare()
        with contextlib.suppress(Exception):
            self.session.close()
