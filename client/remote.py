"""The trainer's side of the wire: a Zenoh connection and the arena groups opened through it.

:class:`Connection` is one Zenoh session with this trainer's liveliness token (the server frees
our arenas when it disappears) and the subscriber our observations arrive on.
:class:`ArenaGroup` is a set of arenas opened (or joined) in one request and stepped in lock
step; it survives a server restart by reopening its arenas and reporting the broken episodes
as truncated. :class:`~overtake.client.environment.RemoteEnvironment` and the Gymnasium
environments are built on these two.

Which server serves an open request: the client asks every server on the network for its
status and picks the one with the most free arenas that can take the whole request (ties: the
fewest groups, then at random), unless ``server`` names one. A server that turns out full in
the meantime passes the request on to the next.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import os
import queue
import secrets
import socket
import threading
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np
import zenoh

from overtake.protocol import codec, errors, keys
from overtake.protocol.messages import (
    Ack,
    Actions,
    BehaviourSpec,
    CloseRequest,
    ErrorReply,
    JoinRequest,
    Message,
    Opened,
    OpenRequest,
    ResetRequest,
    StatusReply,
    StatusRequest,
    Steps,
)
from overtake.protocol.transport import (
    DEFAULT_ENDPOINT,
    SecurityConfig,
    TransportConfig,
    connect_failure_cause,
    open_session,
)

log = logging.getLogger("overtake.client")

M = TypeVar("M", bound=Message)

# Messages dropped (unreadable, or not for us) are logged at most once per this many seconds.
DROPPED_LOG_INTERVAL_S = 5.0
# A request a busy server did not queue is asked again after this pause, doubled each time
# up to the maximum (a flood of requests usually drains within a second: bench/fuzz_wire.py).
BUSY_FIRST_PAUSE_S = 0.05
BUSY_MAX_PAUSE_S = 1.0


@dataclass(frozen=True)
class RemoteConfig:
    """How a trainer reaches simulator servers."""

    connect: tuple[str, ...] = (DEFAULT_ENDPOINT,)
    """Zenoh endpoints: a server's ``--listen`` address or a router's."""
    server: str | None = None
    """Use this server (its ``--name``); by default the least loaded one is picked."""
    connect_timeout_s: float = 5.0
    """How long to keep trying to reach the endpoints before failing with ConnectError."""
    request_timeout_s: float = 10.0
    """How long an open, reset, close or status request may take."""
    step_timeout_s: float = 120.0
    """How long to wait for a step's observations (longer than the server's step deadline)."""
    reconnect_timeout_s: float = 30.0
    """After losing the server, how long to wait for one to reopen the arenas on (0: never)."""
    lease_s: float = 3.0
    """If this trainer's host vanishes (or it freezes), servers free its arenas within this."""
    security: SecurityConfig = field(default_factory=SecurityConfig)
    """usrpwd credentials and TLS certificates (the password from a file or the environment)"""
    trainer_name: str | None = None
    """A readable prefix for this trainer's id in server logs and status. Default: the usrpwd
    user, else "trainer". A router that isolates trainers (overtake-router
    --isolate-trainers) lets a user's session use only ids that begin with its user name."""

    @classmethod
    def from_connect(cls, connect: str | tuple[str, ...] | list[str] | None) -> RemoteConfig:
        """Defaults, with ``connect`` (one endpoint or several; None: the default)."""
        if connect is None:
            return cls()
        return cls(connect=(connect,) if isinstance(connect, str) else tuple(connect))

    def transport(self) -> TransportConfig:
        return TransportConfig(
            mode="client",
            connect=self.connect,
            connect_timeout_s=self.connect_timeout_s,
            lease_s=self.lease_s,
            security=self.security,
        )


def _trainer_id(prefix: str | None) -> str:
    host = "".join(c if c.isalnum() or c in "-_." else "-" for c in socket.gethostname())[:24]
    head = "".join(c if c.isalnum() or c in "-_." else "-" for c in (prefix or "trainer"))
    head = head[: keys.TRAINER_PREFIX_CHARS]
    return f"{head}-{host or 'host'}-{os.getpid()}-{secrets.token_hex(3)}"


def likely_causes(config: RemoteConfig) -> str:
    user = config.security.user_name()
    return (
        "Likely causes: no overtake-server (or Zenoh router) is running there; a wrong host "
        "or port; the server listens on loopback only (start it with --listen "
        "tcp/0.0.0.0:7447 to let other hosts in); a firewall; wrong or missing Zenoh "
        "credentials" + (" (user " + repr(user) + ")" if user else "") + "; a TLS "
        "certificate this side does not trust (--tls-root-ca)."
    )


def unreachable_message(config: RemoteConfig, error: Exception) -> str:
    """Why opening a session failed: the cause found by trying the links by hand (Zenoh only
    says it could not connect), or the likely causes when none could be tried."""
    zenoh_text = str(error).split(" at /")[0].strip()  # drop Zenoh's source location
    cause = connect_failure_cause(config.transport())
    return (
        f"could not connect to {', '.join(config.connect)} within "
        f"{config.connect_timeout_s:g} s ({zenoh_text}). "
        + (f"{cause[0].upper()}{cause[1:]}." if cause else likely_causes(config))
    )


class Connection:
    """One Zenoh session of one trainer."""

    def __init__(self, config: RemoteConfig) -> None:
        self.config = config
        self.trainer = _trainer_id(config.trainer_name or config.security.user_name())
        try:
            self.session = open_session(config.transport())
        except zenoh.ZError as error:
            raise errors.ConnectError(unreachable_message(config, error)) from None
        self._inbox: queue.SimpleQueue[tuple[str, bytes]] = queue.SimpleQueue()
        self._buffered: dict[tuple[str, int], deque[Steps]] = {}
        self._errors: dict[tuple[str, int], deque[errors.ProtocolError]] = {}
        # The (server, group) pairs this connection steps: anything else that arrives is
        # stale or foreign and is dropped.
        self._stepping: set[tuple[str, int]] = set()
        self._servers_lost: set[str] = set()
        # Times each server's token disappeared: a group opened at one count is gone at the
        # next, even if a restarted server of the same name is back by the time we look.
        self._server_epoch: dict[str, int] = {}
        self._lock = threading.Lock()
        self._server_appeared = threading.Event()
        self._token = self.session.liveliness().declare_token(keys.trainer_alive(self.trainer))
        self._subscriber = self.session.declare_subscriber(
            keys.trainer_steps_all(self.trainer),
            lambda sample: self._inbox.put((str(sample.key_expr), sample.payload.to_bytes())),
        )
        self._alive_sub = self.session.liveliness().declare_subscriber(
            keys.ALL_SERVERS_ALIVE, self._on_server_alive, history=True
        )
        self._publishers: dict[str, zenoh.Publisher] = {}
        self._drop_logged_t, self._drops_unlogged = -math.inf, 0
        self.closed = False

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

    def send_actions(self, server: str, actions: Actions) -> None:
        pub = self._publishers.get(server)
        if pub is None:
            pub = self._publishers[server] = self.session.declare_publisher(
                keys.server_actions(server, self.trainer),
                congestion_control=zenoh.CongestionControl.BLOCK,
                priority=zenoh.Priority.DATA_HIGH,
            )
        pub.put(codec.encode(actions))

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
        return self._take(server, group, round_)

    def next_steps(self, server: str, group: int, round_: int, epoch: int) -> Steps:
        """Block until the :class:`Steps` of ``group``'s ``round_`` arrive."""
        deadline = time.monotonic() + self.config.step_timeout_s
        while True:
            steps = self._take(server, group, round_)
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
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise errors.StepTimeout(
                    f"no observations from server {server} for round {round_} of group {group} "
                    f"within {self.config.step_timeout_s:g} s (the server's step deadline may "
                    "be longer; see RemoteConfig.step_timeout_s)"
                )
            try:
                key, payload = self._inbox.get(timeout=min(remaining, 0.5))
            except queue.Empty:
                continue
            if key:
                self._file(key, payload)

    def _file(self, key: str, payload: bytes) -> None:
        sender = key.rsplit("/", 1)[-1]
        try:
            message = codec.decode(payload, Steps)
        except errors.ProtocolError as error:
            self._drop("dropped an unreadable message from server %s: %s", sender, error)
            return
        if isinstance(message, ErrorReply):
            if (sender, message.group) not in self._stepping:
                # Not about a group we step (perhaps garbage sent in our name): say so only.
                self._drop("server %s refused a message in our name: %s", sender, message.message)
                return
            self._errors.setdefault((sender, message.group), deque()).append(
                errors.error_from_code(message.code, f"server {sender}: {message.message}")
            )
            return
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
        with how many went unlogged meanwhile: a flood of garbage in our name (bench/fuzz_wire)
        would otherwise write a line per frame."""
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
        """Start accepting Steps and errors for ``group`` (after opening or joining it)."""
        self.forget(server, group)
        self._stepping.add((server, group))

    def forget(self, server: str, group: int) -> None:
        self._stepping.discard((server, group))
        self._buffered.pop((server, group), None)
        self._errors.pop((server, group), None)

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
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


@dataclass
class ArenaGroup:
    """Arenas opened (or joined) in one request, stepped in lock step."""

    connection: Connection
    request: OpenRequest | JoinRequest
    """What was asked: kept to reopen the same arenas after a server restart."""
    server: str = ""
    group_id: int = -1
    arena_ids: tuple[int, ...] = ()
    ticket: bytes = b""
    spec: BehaviourSpec | None = None
    round: int = 0
    last: Steps | None = None
    _pending_restart: Steps | None = field(default=None, repr=False)
    restarts: int = 0
    epoch: int = 0  # the server's epoch (Connection.epoch) when the group was opened
    server_minor: int = 2
    """The server's minor protocol version (Opened.server_minor; a 1.2 server says none)."""
    trainer_step: int = -1
    """Sent with every Actions (-1: not given): the trainer's step count, which the server
    repeats in its world frames so that recordings of the road share the trainer's timeline."""
    _in_flight: bool = field(default=False, repr=False)
    _early: Steps | None = field(default=None, repr=False)
    _lost: errors.ServerLost | None = field(default=None, repr=False)

    @classmethod
    def open(cls, connection: Connection, request: OpenRequest | JoinRequest) -> ArenaGroup:
        """Open (or join) on the server the module's rule picks; ``request.trainer`` must be
        ``connection.trainer``."""
        if request.trainer != connection.trainer:
            raise ValueError(
                f"the request names trainer {request.trainer!r}, but this "
                f"connection is {connection.trainer!r}"
            )
        group = cls(connection=connection, request=request)
        group._open()
        return group

    def _open(self, reseed: bool = True) -> None:
        request, conn = self.request, self.connection
        if isinstance(request, JoinRequest):
            if conn.config.server is None:
                raise ValueError("joining an arena needs the server's name (RemoteConfig.server)")
            epoch = conn.epoch(conn.config.server)
            opened = conn.request(conn.config.server, request, Opened)
        else:
            if not reseed:
                # After a restart the first episodes must not replay: fresh seeds.
                request = dataclasses.replace(request, seed=None)
            last_error: errors.ProtocolError | None = None
            for server in conn.candidates(request.arenas):
                try:
                    epoch = conn.epoch(server)
                    opened = conn.request(server, request, Opened)
                    break
                except (errors.ServerFull, errors.ServerBusy, errors.ServerLost) as error:
                    last_error = error
            else:
                assert last_error is not None
                raise last_error
        # The epoch seen before asking: a restart between the reply and now still counts.
        self.epoch = epoch
        self.server, self.group_id, self.arena_ids = opened.server, opened.group, opened.arenas
        conn.track(self.server, self.group_id)
        self.ticket, self.spec = opened.ticket, opened.spec
        self.server_minor = opened.server_minor
        self.round = opened.steps.round
        self.last = opened.steps

    @property
    def agents(self) -> np.ndarray:
        assert self.last is not None
        return self.last.agents

    def reset(self, arenas: tuple[int, ...], seeds: tuple[int | None, ...]) -> Steps:
        """New episodes in ``arenas`` (indices in the group); the Steps of all our agents."""
        if self._in_flight:
            raise RuntimeError(
                f"group {self.group_id}: reset while a step is in flight; receive it first"
            )
        conn = self.connection
        self._pending_restart = None
        if self._server_restarted():
            self._reopen()
        for attempt in (1, 2):
            try:
                steps = conn.request(
                    self.server,
                    ResetRequest(
                        trainer=conn.trainer,
                        ticket=self.ticket,
                        group=self.group_id,
                        arenas=arenas,
                        seeds=seeds,
                    ),
                    Steps,
                )
                break
            except errors.ServerLost:
                if attempt == 2:
                    raise
                self._reopen()
        conn.track(self.server, self.group_id)  # rounds stepped before the reset are stale
        self.round = steps.round
        self.last = steps
        return steps

    def step(self, agents: np.ndarray, actions: np.ndarray, retire: Sequence[int] = ()) -> Steps:
        """Send our actions for this round and wait for the next round's Steps.

        ``retire``: agent ids whose cars leave the road before this round and stay off until
        their arena is reset (protocol 1.3; see :attr:`server_minor`)."""
        self.send(agents, actions, retire)
        return self.receive()

    def send(self, agents: np.ndarray, actions: np.ndarray, retire: Sequence[int] = ()) -> None:
        """The first half of :meth:`step`: our actions for this round go out, and the server
        plays the round while the caller does something else; :meth:`receive` takes its
        Steps. A lost server is reported by :meth:`receive`, as :meth:`step` reports it."""
        if self._in_flight:
            raise RuntimeError(
                f"group {self.group_id}: actions sent twice for round {self.round}; "
                "receive the round's Steps first"
            )
        self._in_flight = True
        self._early, self._lost = None, None
        if self._pending_restart is not None:
            return  # the reopened arenas' first Steps are here already: nothing to send
        conn = self.connection
        try:
            if self._server_restarted():
                raise errors.ServerLost(
                    f"server {self.server} restarted since group {self.group_id} was opened"
                )
            # Behind (the group played our round at the deadline)? Then that round's Steps are
            # here already, marked late; our actions would be stale, so they are not sent.
            self._early = conn.arrived(self.server, self.group_id, self.round + 1)
            if self._early is None:
                conn.send_actions(
                    self.server,
                    Actions(
                        trainer=conn.trainer,
                        ticket=self.ticket,
                        group=self.group_id,
                        round=self.round,
                        agents=np.asarray(agents, dtype=np.int32),
                        actions=np.asarray(actions, dtype=np.int64),
                        trainer_step=self.trainer_step,
                        retire=np.asarray(retire, dtype=np.int32) if len(retire) else None,
                    ),
                )
        except errors.ServerLost as error:
            self._lost = error

    def receive(self) -> Steps:
        """The second half of :meth:`step`: wait for the Steps of the round :meth:`send`
        sent."""
        if not self._in_flight:
            raise RuntimeError(f"group {self.group_id}: no actions sent to receive Steps for")
        self._in_flight = False
        if self._pending_restart is not None:
            # The server was restarted: the step after the broken episodes starts the new ones.
            pending, self._pending_restart = self._pending_restart, None
            self.last = pending
            return pending
        lost, steps = self._lost, self._early
        self._lost, self._early = None, None
        if lost is not None:
            return self._survive(lost)
        if steps is None:
            try:
                steps = self.connection.next_steps(
                    self.server, self.group_id, self.round + 1, self.epoch
                )
            except errors.ServerLost as error:
                return self._survive(error)
        self.round = steps.round
        self.last = steps
        return steps

    def _server_restarted(self) -> bool:
        return self.connection.epoch(self.server) != self.epoch

    def _survive(self, error: errors.ServerLost) -> Steps:
        """Reopen our arenas elsewhere (or on the restarted server); the episodes broke."""
        if isinstance(self.request, JoinRequest) or self.connection.config.reconnect_timeout_s <= 0:
            raise error
        broken = self.last
        assert broken is not None
        log.warning("%s; reopening %d arena(s)", error, len(self.arena_ids))
        self._reopen()
        self.restarts += 1
        fresh = self.last
        assert fresh is not None
        self._pending_restart = fresh
        truncated = Steps(
            server=broken.server,
            group=broken.group,
            round=broken.round + 1,
            agents=broken.agents,
            observations=broken.observations,
            reward=np.zeros_like(broken.reward),
            terminated=np.zeros_like(broken.terminated),
            # Agents that had just ended were reported already; the rest are cut short.
            truncated=~broken.ended,
            action_applied=np.full_like(broken.action_applied, -1),
            late=np.zeros_like(broken.late),
            action_mask=broken.action_mask,
            reward_terms=np.zeros_like(broken.reward_terms),
            metrics=broken.metrics,
        )
        self.last = truncated
        return truncated

    def _reopen(self) -> None:
        conn = self.connection
        conn.forget(self.server, self.group_id)
        deadline = time.monotonic() + conn.config.reconnect_timeout_s
        while True:
            try:
                self._open(reseed=False)
                return
            # Not on a timeout: the server may have opened the arenas anyway, and asking
            # again would open them twice.
            except (errors.ConnectError, errors.ServerLost) as error:
                if time.monotonic() >= deadline:
                    raise errors.ServerLost(
                        f"lost server {self.server} and found no server to reopen "
                        f"{len(self.arena_ids)} arena(s) on within "
                        f"{conn.config.reconnect_timeout_s:g} s ({error})"
                    ) from None
                time.sleep(0.2)  # polling for a server to come back; nothing to wait on

    def close(self) -> None:
        conn = self.connection
        if conn.closed or self.group_id < 0:
            return
        try:
            conn.request(
                self.server,
                CloseRequest(trainer=conn.trainer, ticket=self.ticket, group=self.group_id),
                Ack,
            )
        except errors.ProtocolError as error:
            log.debug("close of group %d: %s", self.group_id, error)
        conn.forget(self.server, self.group_id)
        self.group_id = -1
