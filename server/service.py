"""The simulator server: arena groups served to trainers over Zenoh.

Zenoh's threads only enqueue what arrives; one loop thread decodes, validates, steps groups and
publishes, so the simulation needs no locks and a bad message can only ever produce an error
reply or a log line. Observations and actions travel with blocking congestion control (no
step is silently lost); world frames for spectators are dropped under congestion, so watching
never holds the simulation back.
"""

from __future__ import annotations

import contextlib
import logging
import os
import queue
import secrets
import signal
import socket
import sys
import threading
import time
from dataclasses import dataclass, field
from importlib import metadata
from typing import Any

import zenoh

from overtake.protocol import codec, errors, keys
from overtake.protocol.messages import (
    PROTOCOL_VERSION,
    Ack,
    Actions,
    CloseRequest,
    ErrorReply,
    JoinRequest,
    Message,
    Opened,
    OpenRequest,
    ResetRequest,
    StatusReply,
    StatusRequest,
)
from overtake.protocol.transport import (
    DEFAULT_ENDPOINT,
    SecurityConfig,
    TransportConfig,
    open_session,
    warn_if_unconnected,
    warn_if_unguarded,
)
from overtake.viz.recording import RecordingConfig

from .errors import StartError
from .groups import Group, next_to_step
from .recorder import ServerRecorder

log = logging.getLogger("overtake.server")

# What Zenoh's threads hand the loop: small records, decoded and checked only by the loop.


@dataclass(frozen=True)
class _Query:
    query: zenoh.Query
    payload: bytes


@dataclass(frozen=True)
class _ActionsPut:
    key: str
    payload: bytes


@dataclass(frozen=True)
class _Liveliness:
    key: str
    present: bool


@dataclass(frozen=True)
class _Wake:
    """Nothing to do but look at the clock (a stop request, or a deadline)."""


_Event = _Query | _ActionsPut | _Liveliness | _Wake
_WAKE = _Wake()
# Events handled before the ready groups step: bounds what a flood of messages can delay.
MAX_EVENTS_PER_PASS = 256
# What a flood may queue before the loop reads it (bench/fuzz_wire.py: a million unreadable
# actions on one key queued 150 MiB). Actions waiting per key (per trainer name): a trainer in
# lock step has one at a time, so only a flood on its key reaches the bound. Requests waiting
# in all (their sender is not known before decoding): beyond it a request goes unanswered and
# its sender's timeout says so.
MAX_QUEUED_ACTIONS_PER_KEY = 64
MAX_QUEUED_REQUESTS = 1024
# At most one warning about dropped frames per this many seconds.
DROPPED_REPORT_INTERVAL_S = 5.0


# With its sink on, a server logs every arena one round in this many: logging every round
# costs trainers 20-30% of their steps per second, one in ten a few per cent (bench/RESULTS.md).
SERVER_RECORD_EVERY = 10


def busy_reply(server: str) -> ErrorReply:
    """The answer to a request that finds MAX_QUEUED_REQUESTS already waiting."""
    return ErrorReply(
        code=errors.ServerBusy.code,
        message=f"server {server} is busy: {MAX_QUEUED_REQUESTS} requests are waiting "
        "already, so this one was not queued; ask again",
    )


def default_server_name() -> str:
    host = "".join(c if c.isalnum() or c in "-_." else "-" for c in socket.gethostname())
    return f"sim-{host[:40] or 'host'}-{os.getpid()}"


@dataclass(frozen=True)
class ServerConfig:
    """An ``overtake-server`` process."""

    name: str = field(default_factory=default_server_name)
    """Unique on the Zenoh network; it is part of every key this server serves."""
    listen: tuple[str, ...] = (DEFAULT_ENDPOINT,)
    """Endpoints to listen on. Loopback by default; ``tcp/0.0.0.0:7447`` lets other hosts in;
    none (``--listen`` alone) when the server only joins a router through ``--connect``."""
    connect: tuple[str, ...] = ()
    """Zenoh routers (or peers) to connect to, e.g. ``tcp/router:7447``."""
    max_arenas: int = 256
    """Arenas this server holds at once; an open request beyond it is refused as full."""
    max_arenas_per_trainer: int | None = None
    """Arenas one trainer may hold here at once (opened or joined); beyond it an open or join
    is refused as full, and the trainer's client tries the next server. Default: no limit
    below --max-arenas. On a server others share, set it so that one trainer (or a stranger
    who reached the port) cannot take all of it."""
    step_deadline_s: float = 30.0
    """How long a round waits for late trainers once another trainer of the group has acted.
    Generous, since a learner may pause for network updates; late agents get the default
    action (keep) and are reported as late."""
    world_rate_hz: float = 10.0
    """World frames per second per arena for spectators (0 turns them off)."""
    lease_s: float = 3.0
    """Trainers notice within this that this server's host vanished (a trainer's own lease,
    RemoteConfig.lease_s, bounds how soon its arenas are freed when its host vanishes)."""
    security: SecurityConfig = field(default_factory=SecurityConfig)
    """usrpwd credentials (when connecting to a router that asks for them, and the users this
    server admits) and TLS certificates (for tls/ endpoints)"""
    log_level: str = "info"
    recording: RecordingConfig = field(
        default_factory=lambda: RecordingConfig(sink="off", record_every=SERVER_RECORD_EVERY)
    )
    """Rerun: this server logs every arena it steps itself (default off; spectators watch
    without it), one round in --record-every. With --sink file the .rrd defaults to
    runs/server/<name>.rrd."""

    def transport(self) -> TransportConfig:
        return TransportConfig(
            mode="peer",
            listen=self.listen,
            connect=self.connect,
            lease_s=self.lease_s,
            security=self.security,
        )


def _package_version() -> str:
    try:
        return metadata.version("overtake")
    except metadata.PackageNotFoundError:  # pragma: no cover - running from a bare checkout
        return "unknown"


class SimulatorServer:
    """Serves arena groups over a Zenoh session. :meth:`serve` runs until :meth:`stop`."""

    def __init__(self, config: ServerConfig, session: zenoh.Session | None = None) -> None:
        keys.server_request(config.name)  # checks the name
        if config.max_arenas < 1:
            raise ValueError(f"max_arenas must be >= 1, got {config.max_arenas}")
        if config.step_deadline_s <= 0:
            raise ValueError(f"step_deadline_s must be > 0, got {config.step_deadline_s}")
        self.config = config
        self.name = config.name
        self._events: queue.SimpleQueue[_Event] = queue.SimpleQueue()
        # Frames queued and not yet handled, counted by Zenoh's threads and the loop alike.
        self._queue_lock = threading.Lock()
        self._queued_actions: dict[str, int] = {}
        self._queued_requests = 0
        self._dropped = 0
        self._dropped_reported = 0
        self._dropped_report_t = 0.0
        self._busy_frame = codec.encode(busy_reply(config.name))
        self._stopping = threading.Event()
        self._own_session = session is None
        self.session = session if session is not None else open_session(config.transport())
        self.groups: dict[int, Group] = {}
        self._arena_index: dict[int, tuple[int, int]] = {}  # arena id -> (group, index)
        self._next_arena = 0
        self._alive_trainers: set[str] = set()
        self._step_pubs: dict[str, zenoh.Publisher] = {}
        self._world_pubs: dict[int, zenoh.Publisher] = {}
        self._last_world: dict[int, float] = {}
        self._started = time.monotonic()
        self._declared: list[Any] = []
        self._declare()
        self.recorder: ServerRecorder | None = None
        if config.recording.sink != "off":
            try:
                self.recorder = ServerRecorder(config.recording, self.name)
            except BaseException:
                self.close()
                raise

    # --- Zenoh plumbing (callbacks only enqueue) -------------------------------------------

    def _declare(self) -> None:
        existing = [
            r
            for r in self.session.liveliness().get(keys.server_alive(self.name), timeout=1.0)
            if r.ok
        ]
        if existing:
            raise RuntimeError(
                f"a server named {self.name!r} is already on this Zenoh network; "
                "give this one another --name"
            )
        s = self.session
        self._declared.append(
            s.declare_queryable(keys.server_request(self.name), self._enqueue_query)
        )
        self._declared.append(
            s.declare_subscriber(keys.server_actions_all(self.name), self._enqueue_actions)
        )
        self._declared.append(
            s.liveliness().declare_subscriber(
                keys.ALL_TRAINERS_ALIVE,
                lambda sample: self._events.put(
                    _Liveliness(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)
                ),
                history=True,
            )
        )
        self._token = s.liveliness().declare_token(keys.server_alive(self.name))

    def _enqueue_query(self, query: zenoh.Query) -> None:
        """Zenoh's thread: queue a request, unless a flood already filled the queue; then it
        is answered busy at once (a prepared frame: no decoding, nothing kept), so that an
        honest asker caught in the flood hears why and asks again instead of timing out."""
        with self._queue_lock:
            full = self._queued_requests >= MAX_QUEUED_REQUESTS
            if full:
                self._dropped += 1
            else:
                self._queued_requests += 1
        if full:
            with contextlib.suppress(Exception), query:
                query.reply(keys.server_request(self.name), self._busy_frame)
            return
        self._events.put(_Query(query, query.payload.to_bytes() if query.payload else b""))

    def _enqueue_actions(self, sample: zenoh.Sample) -> None:
        """Zenoh's thread: queue actions, unless their key already has its share queued."""
        key = str(sample.key_expr)
        with self._queue_lock:
            waiting = self._queued_actions.get(key, 0)
            if waiting >= MAX_QUEUED_ACTIONS_PER_KEY:
                self._dropped += 1
                return
            self._queued_actions[key] = waiting + 1
        self._events.put(_ActionsPut(key, sample.payload.to_bytes()))

    def _dequeued(self, event: _Event) -> None:
        """The loop took ``event``: it no longer counts against its queue's bound."""
        with self._queue_lock:
            if isinstance(event, _Query):
                self._queued_requests -= 1
            elif isinstance(event, _ActionsPut):
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

    # --- main loop ------------------------------------------------------------------------------

    def stop(self) -> None:
        self._stopping.set()
        self._events.put(_WAKE)

    def serve(self) -> None:
        log.info(
            "server %s serving (%s), up to %d arenas, step deadline %.1f s",
            self.name,
            self.config.transport().describe(),
            self.config.max_arenas,
            self.config.step_deadline_s,
        )
        if self.recorder is not None:
            log.info(
                "recording every arena every %d round(s) to %s",
                self.config.recording.record_every,
                self.recorder.where,
            )
        try:
            while not self._stopping.is_set():
                # Take what has arrived before stepping (arrivals together make a group ready
                # at once), but not without bound: a flood must not keep the groups from
                # stepping.
                for _ in range(MAX_EVENTS_PER_PASS):
                    try:
                        self._handle(self._events.get_nowait())
                    except queue.Empty:
                        break
                group = next_to_step(self.groups.values(), time.monotonic())
                if group is not None:
                    self._step_group(group)
                    continue
                try:
                    event = self._events.get(timeout=self._next_timeout())
                except queue.Empty:
                    event = _WAKE
                self._handle(event)
        finally:
            self.close()

    def close(self) -> None:
        # Whatever is already gone with the session needs no undeclaring.
        for obj in self._declared:
            with contextlib.suppress(Exception):
                obj.undeclare()
        self._declared.clear()
        with contextlib.suppress(Exception):
            self._token.undeclare()
        if self._own_session and not self.session.is_closed():
            self.session.close()
        recorder = getattr(self, "recorder", None)
        if recorder is not None:
            recorder.close()
            self.recorder = None
        log.info("server %s stopped", self.name)

    def _next_timeout(self) -> float:
        deadlines = [g.deadline for g in self.groups.values() if g.deadline is not None]
        if not deadlines:
            return 1.0
        return min(max(min(deadlines) - time.monotonic(), 0.0), 1.0)

    def _handle(self, event: _Event) -> None:
        self._dequeued(event)
        try:
            if isinstance(event, _Query):
                self._on_query(event.query, event.payload)
            elif isinstance(event, _ActionsPut):
                self._on_actions(event.key, event.payload)
            elif isinstance(event, _Liveliness):
                self._on_alive(event.key, event.present)
        except Exception:  # the loop must survive anything; a bug shows as a log line
            log.exception("unexpected error handling %s", type(event).__name__)

    # --- requests -------------------------------------------------------------------------------

    def _reply(self, query: zenoh.Query, message: Message) -> None:
        with query:
            query.reply(keys.server_request(self.name), codec.encode(message))

    def _on_query(self, query: zenoh.Query, payload: bytes) -> None:
        try:
            request: Message = codec.decode(
                payload, (StatusRequest, OpenRequest, JoinRequest, ResetRequest, CloseRequest)
            )
            if isinstance(request, ErrorReply):
                raise errors.DecodeError(
                    "expected a request (status_request, open, join, "
                    "reset or close), got an error reply"
                )
            reply = self._dispatch(request)
        except errors.ProtocolError as error:
            log.info("refused a request: %s", error)
            reply = ErrorReply(code=error.code, message=str(error))
        except Exception as error:  # a bug here must still answer, not leave the asker waiting
            log.exception("failed to serve a request")
            reply = ErrorReply(
                code=errors.ProtocolError.code,
                message=f"server {self.name} failed: {type(error).__name__}: {error}",
            )
        self._reply(query, reply)

    def _dispatch(self, request: Message) -> Message:
        if isinstance(request, StatusRequest):
            return self.status()
        if isinstance(request, OpenRequest):
            return self._open(request)
        if isinstance(request, JoinRequest):
            return self._join(request)
        if isinstance(request, ResetRequest):
            return self._group(request.group).reset(
                request.trainer, request.ticket, request.arenas, request.seeds
            )
        if isinstance(request, CloseRequest):
            group = self._group(request.group)
            group.member(request.trainer, request.ticket)
            self._leave(group, request.trainer, "closed")
            return Ack(message=f"left group {request.group}")
        raise errors.DecodeError(f"not a request: {request.TYPE}")  # pragma: no cover

    def status(self) -> StatusReply:
        with self._queue_lock:
            queued_actions = sum(self._queued_actions.values())
            # The status request being answered has left the queue already.
            queued_requests, dropped = self._queued_requests, self._dropped
        return StatusReply(
            server=self.name,
            package_version=_package_version(),
            max_arenas=self.config.max_arenas,
            arenas_used=len(self._arena_index),
            step_deadline_s=self.config.step_deadline_s,
            uptime_s=time.monotonic() - self._started,
            groups=tuple(g.status() for g in self.groups.values()),
            queued_actions=queued_actions,
            queued_requests=queued_requests,
            dropped_frames=dropped,
        )

    def _require_alive(self, trainer: str) -> None:
        if trainer in self._alive_trainers:
            return
        # Its token may not have reached us yet: ask once.
        replies = self.session.liveliness().get(keys.trainer_alive(trainer), timeout=1.0)
        if not any(r.ok for r in replies):
            raise errors.NotOwner(
                f"trainer {trainer!r} holds no liveliness token "
                f"({keys.trainer_alive(trainer)}); open arenas through "
                "overtake.client, which declares one"
            )
        self._alive_trainers.add(trainer)

    def _arenas_of(self, trainer: str) -> int:
        """Arenas in which ``trainer`` holds cars."""
        return sum(
            int(member.slots.any(axis=1).sum())
            for group in self.groups.values()
            if (member := group.members.get(trainer)) is not None
        )

    def _check_trainer_limit(self, trainer: str, more: int) -> None:
        limit = self.config.max_arenas_per_trainer
        if limit is None:
            return
        held = self._arenas_of(trainer)
        if held + more > limit:
            raise errors.ServerFull(
                f"server {self.name} lets one trainer hold at most {limit} arena(s) "
                f"(--max-arenas-per-trainer); {trainer} holds {held}, asked for {more} more"
            )

    def _open(self, request: OpenRequest) -> Opened:
        self._require_alive(request.trainer)
        self._check_trainer_limit(request.trainer, request.arenas)
        free = self.config.max_arenas - len(self._arena_index)
        if request.arenas > free:
            raise errors.ServerFull(
                f"server {self.name} has {free} free arena(s) of "
                f"{self.config.max_arenas}, asked for {request.arenas}"
            )
        arena_ids = list(range(self._next_arena, self._next_arena + request.arenas))
        group = Group.open(
            self._new_group_id(),
            self.name,
            arena_ids,
            request.preset,
            dict(request.overrides),
            request.agents_per_arena,
            request.seed,
        )
        for index in range(request.arenas):
            group.claim(request.trainer, index, request.claim, fresh=True)
        opened = self._opened(group, request.trainer)
        # Registered only once the reply exists: a failure above leaves nothing behind.
        self._next_arena += request.arenas
        self.groups[group.group_id] = group
        for index, arena in enumerate(arena_ids):
            self._arena_index[arena] = (group.group_id, index)
        log.info(
            "trainer %s opened group %d: %d arena(s) %s of %s, %d agent(s) each",
            request.trainer,
            group.group_id,
            request.arenas,
            _span(arena_ids),
            request.preset,
            request.agents_per_arena,
        )
        return opened

    def _new_group_id(self) -> int:
        # Random rather than counted: a restarted server never reuses the id of a group its
        # previous life served, so late messages about the old one cannot be mistaken.
        while True:
            group_id = secrets.randbelow(2**31)
            if group_id not in self.groups:
                return group_id

    def _join(self, request: JoinRequest) -> Opened:
        self._require_alive(request.trainer)
        where = self._arena_index.get(request.arena)
        if where is None:
            raise errors.UnknownArena(
                f"server {self.name} has no arena {request.arena}; its "
                f"arenas are {_span(sorted(self._arena_index))}"
            )
        group = self.groups[where[0]]
        member = group.members.get(request.trainer)
        if member is None or not member.slots[where[1]].any():
            self._check_trainer_limit(request.trainer, 1)
        group.claim(request.trainer, where[1], request.agents, fresh=False)
        log.info(
            "trainer %s joined arena %d (group %d) with %d agent(s)",
            request.trainer,
            request.arena,
            group.group_id,
            request.agents,
        )
        return self._opened(group, request.trainer)

    def _opened(self, group: Group, trainer: str) -> Opened:
        self._publisher_for(trainer)
        member = group.members[trainer]
        return Opened(
            server=self.name,
            group=group.group_id,
            arenas=tuple(group.arena_ids),
            ticket=member.ticket,
            spec=group.spec,
            steps=group.current_steps(trainer),
            server_minor=PROTOCOL_VERSION[1],
        )

    def _group(self, group_id: int) -> Group:
        group = self.groups.get(group_id)
        if group is None:
            raise errors.UnknownArena(
                f"server {self.name} has no group {group_id} (closed, or never opened)"
            )
        return group

    # --- actions and rounds -----------------------------------------------------------------

    def _on_actions(self, key: str, payload: bytes) -> None:
        try:
            _, trainer = keys.parse_server_actions(key)
        except errors.ProtocolError as error:
            log.warning("dropped actions on a malformed key: %s", error)
            return
        actions: Message | None = None
        try:
            actions = codec.decode(payload, Actions)
            if not isinstance(actions, Actions):
                raise errors.DecodeError(f"expected actions, got {actions.TYPE}")
            if actions.trainer != trainer:
                # Someone speaking on another trainer's key: not an answer anybody waits for.
                log.warning(
                    "dropped actions on %s's key that claim to come from %s",
                    trainer,
                    actions.trainer,
                )
                return
            self._group(actions.group).accept(actions, self.config.step_deadline_s)
        except errors.StaleActions as error:
            log.debug("dropped late actions from %s: %s", trainer, error)
        except errors.WrongTicket as error:
            # Not from the session that owns these agents: replying on the named trainer's
            # key would only disturb that trainer.
            log.warning("dropped actions in %s's name: %s", trainer, error)
        except errors.ProtocolError as error:
            log.info("refused actions from %s: %s", trainer, error)
            if trainer not in self._alive_trainers:
                # Nobody of that name is connected: no reply to a key nobody reads. Each new
                # key a reply goes to costs Zenoh memory for good (bench/fuzz_wire.py), so a
                # stranger inventing names must not make the server write to them.
                return
            group = actions.group if isinstance(actions, Actions) else None
            self._send(trainer, ErrorReply(code=error.code, message=str(error), group=group))

    def _step_group(self, group: Group) -> None:
        """Step one group, send each member its observations, publish and record it."""
        try:
            steps = group.step()
            for trainer, message in steps.items():
                self._send(trainer, message)
            self._publish_world(group, time.monotonic())
            if self.recorder is not None and self.recorder.wants(group.round):
                self._record(group)
        except Exception as error:
            # One group's failure is that group's end, not the server's.
            log.exception("group %d failed to step; closing it", group.group_id)
            reply = ErrorReply(
                code=errors.ProtocolError.code,
                group=group.group_id,
                message=f"server {self.name} closed group "
                f"{group.group_id} after an internal error: "
                f"{type(error).__name__}: {error}",
            )
            for trainer in list(group.members):
                try:
                    self._send(trainer, reply)
                except Exception:  # pragma: no cover - the session itself is failing
                    log.exception("could not tell %s", trainer)
                self._leave(group, trainer, "internal error")

    def _record(self, group: Group) -> None:
        """Hand the recorder this round's frames; a failure here costs the recording a
        frame and a log line, never the group its trainers."""
        assert self.recorder is not None
        try:
            observations = group.latest_observations()
            for index in range(len(group.arena_ids)):
                if not self.recorder.has_room():
                    self.recorder.count_dropped(len(group.arena_ids) - index)
                    break
                self.recorder.offer(group.world_frame(index, observations))
        except Exception:
            log.exception("could not record group %d's round %d", group.group_id, group.round)

    def _publisher_for(self, trainer: str) -> zenoh.Publisher:
        pub = self._step_pubs.get(trainer)
        if pub is None:
            pub = self.session.declare_publisher(
                keys.trainer_steps(trainer, self.name),
                congestion_control=zenoh.CongestionControl.BLOCK,
                priority=zenoh.Priority.DATA_HIGH,
            )
            self._step_pubs[trainer] = pub
        return pub

    def _send(self, trainer: str, message: Message) -> None:
        pub = self._step_pubs.get(trainer)
        if pub is not None:
            pub.put(codec.encode(message))
        else:  # a trainer with no arenas here (an error reply): no publisher kept for it
            self.session.put(
                keys.trainer_steps(trainer, self.name),
                codec.encode(message),
                congestion_control=zenoh.CongestionControl.BLOCK,
            )

    def _publish_world(self, group: Group, now: float) -> None:
        rate = self.config.world_rate_hz
        if rate <= 0 or now - self._last_world.get(group.group_id, 0.0) < 1.0 / rate:
            return
        self._last_world[group.group_id] = now
        observations = None
        for index, arena in enumerate(group.arena_ids):
            pub = self._world_pubs.get(arena)
            if pub is None:
                pub = self._world_pubs[arena] = self.session.declare_publisher(
                    keys.world(self.name, arena),
                    congestion_control=zenoh.CongestionControl.DROP,
                    priority=zenoh.Priority.DATA_LOW,
                )
            # zenoh 1.10's stubs say bool; it is a MatchingStatus.
            if not pub.matching_status.matching:  # type: ignore[attr-defined]
                continue  # nobody watches this arena: no frame is even encoded
            if observations is None:
                observations = group.latest_observations()
            pub.put(codec.encode(group.world_frame(index, observations)))

    # --- trainers leaving ---------------------------------------------------------------------

    def _on_alive(self, key: str, present: bool) -> None:
        try:
            trainer = keys.parse_trainer_alive(key)
        except errors.ProtocolError:
            return
        if present:
            self._alive_trainers.add(trainer)
            return
        self._alive_trainers.discard(trainer)
        for group in list(self.groups.values()):
            if trainer in group.members:
                self._leave(group, trainer, "gone (liveliness token lost)")
        pub = self._step_pubs.pop(trainer, None)
        if pub is not None:
            pub.undeclare()

    def _leave(self, group: Group, trainer: str, why: str) -> None:
        group.leave(trainer)
        if group.members:
            log.info(
                "trainer %s left group %d (%s); its cars are off the road",
                trainer,
                group.group_id,
                why,
            )
            return
        self.groups.pop(group.group_id)
        for arena in group.arena_ids:
            self._arena_index.pop(arena, None)
            pub = self._world_pubs.pop(arena, None)
            if pub is not None:
                pub.undeclare()
        self._last_world.pop(group.group_id, None)
        log.info(
            "trainer %s left group %d (%s); arenas %s freed after %d rounds",
            trainer,
            group.group_id,
            why,
            _span(group.arena_ids),
            group.rounds_done,
        )


def _span(ids: list[int]) -> str:
    if not ids:
        return "none"
    if len(ids) > 1 and ids == list(range(ids[0], ids[-1] + 1)):
        return f"{ids[0]}-{ids[-1]}"
    return ", ".join(map(str, ids))


def main(config: ServerConfig) -> None:
    """Run a server until SIGINT or SIGTERM."""
    logging.basicConfig(
        level=config.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    zenoh.init_log_from_env_or("error")
    try:
        server = SimulatorServer(config)
    except zenoh.ZError as error:
        raise StartError(
            f"could not open the Zenoh session ({config.transport().describe()}): "
            f"{error}. Is the port in use, or the router unreachable?"
        ) from None
    except (RuntimeError, errors.ProtocolError) as error:
        raise StartError(str(error)) from None
    warn_if_unconnected(server.session, config.transport(), log)
    warn_if_unguarded(config.transport(), log)

    def on_signal(signum: int, _frame: Any) -> None:
        log.info("received %s, shutting down", signal.Signals(signum).name)
        server.stop()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    server.serve()


def cli() -> None:
    import tyro

    config = tyro.cli(
        ServerConfig,
        config=(tyro.conf.OmitArgPrefixes,),
        description="overtake-server: the highway simulator, served to trainers over Zenoh",
    )
    try:
        main(config)
    except StartError as error:
        sys.exit(f"overtake-server: {error}")
