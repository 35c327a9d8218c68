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
import threading
import time
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor
from importlib import metadata
from typing import Any

import zenoh

from overtake.ipc.shared_memory import sweep_orphans
from overtake.ipc.transport import on_zenoh_thread, open_session
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
    RestoreRequest,
    ShmOffer,
    SnapshotRequest,
    StatusReply,
    StatusRequest,
)

from ..engine.world import group_world_frame
from .arenas import ArenaRegistry, ready_to_step
from .group_state import keep_state, restore_state
from .groups import Group
from .inbox import (
    MAX_EVENTS_PER_PASS,
    WAKE,
    ActionsArrived,
    ActionsRung,
    Event,
    Inbox,
    QueryArrived,
    TrainerPresence,
)
from .outbox import Outbox
from .recorder import ServerRecorder
from .server_config import ServerConfig

log = logging.getLogger("overtake.server")
# What a query may ask.
_REQUESTS = (
    StatusRequest, OpenRequest, JoinRequest, ResetRequest, SnapshotRequest, RestoreRequest,
    CloseRequest,
)  # fmt: skip

# The weight of the latest round in the average time trainers take to answer one (_spin).
ANSWER_AVERAGE_WEIGHT = 0.2


def _package_version() -> str:
    try:
        return metadata.version("overtake")
    except metadata.PackageNotFoundError:  # pragma: no cover - running from a bare checkout
        return "unknown"


class SimulatorServer:
    """Serves arena groups over a Zenoh session. :meth:`serve` runs until :meth:`stop`."""

    def __init__(self, config: ServerConfig, session: zenoh.Session | None = None) -> None:
        keys.server_request(config.name)  # checks the name
        if config.step_threads < 1:
            raise ValueError(f"step_threads must be >= 1, got {config.step_threads}")
        if config.max_arenas < 1:
            raise ValueError(f"max_arenas must be >= 1, got {config.max_arenas}")
        if config.step_deadline_s <= 0:
            raise ValueError(f"step_deadline_s must be > 0, got {config.step_deadline_s}")
        self.config = config
        self.name = config.name
        self.inbox = Inbox(config.name)
        self._stopping = threading.Event()
        self._own_session = session is None
        self.session = session if session is not None else open_session(config.session_config())
        self.arenas = ArenaRegistry(self.name, config.max_arenas, config.max_arenas_per_trainer)
        self._alive_trainers: set[str] = set()
        self.outbox = Outbox(self.session, config, self.inbox.on_ring)
        self._pool: ThreadPoolExecutor | None = None
        self.parallel_passes = 0
        # How long trainers on the shared-memory channel have been taking to answer a round
        # (an average): the loop spins only while it is within spin_s (see _spin).
        self._answer_s = 0.0
        self._round_sent = time.perf_counter()
        """Passes that stepped several groups at once (on the stepping threads)."""
        if config.shared_memory:
            swept = sweep_orphans()
            if swept:
                log.info("removed %d segment(s) a dead process left in shared memory", len(swept))
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
        # Zenoh's threads only enqueue (server/service/inbox.py), on Zenoh's own receiving thread
        # (no Python thread a declaration to wake and hand the GIL to); the loop does the rest.
        inbox = self.inbox
        self._declared += [
            s.declare_queryable(keys.server_request(self.name), on_zenoh_thread(inbox.on_query)),
            s.declare_subscriber(
                keys.server_actions_all(self.name), on_zenoh_thread(inbox.on_actions)
            ),
            s.liveliness().declare_subscriber(
                keys.ALL_TRAINERS_ALIVE, on_zenoh_thread(inbox.on_presence), history=True
            ),
        ]
        self._token = s.liveliness().declare_token(keys.server_alive(self.name))

    # --- main loop ------------------------------------------------------------------------------

    def stop(self) -> None:
        self._stopping.set()
        self.inbox.wake()

    def serve(self) -> None:
        log.info(
            "server %s serving (%s), up to %d arenas, step deadline %.1f s",
            self.name,
            self.config.session_config().describe(),
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
                    arrived = self.inbox.take()
                    if arrived is None:
                        break
                    self._handle(arrived)
                ready = ready_to_step(
                    self.arenas.groups.values(), time.monotonic(), self.config.step_threads
                )
                if ready:
                    self._step_groups(ready)
                    continue
                if self._spin():
                    continue
                with self.outbox.asleep():
                    arrived = self.inbox.take(self._next_timeout())
                self._handle(arrived or WAKE)
        finally:
            self.close()

    def _spin(self) -> bool:
        """With trainers on the shared-memory channel answering within ``spin_s`` on average,
        wait up to ``spin_s`` for an event or a ring, yielding the core at every look
        (``overtake.ipc.doorbell`` says why); whether something came. A ring is handled
        here, not through the bell's thread. Trainers that take longer (a learner updating
        between rounds) are not spun for: the spin would take a core their update uses
        (bench/RESULTS.md, issue 47)."""
        spin_s = self.config.spin_s
        if spin_s <= 0 or not self.outbox.has_offered or self._answer_s > spin_s:
            return False
        started = time.perf_counter()
        while time.perf_counter() - started < spin_s and not self._stopping.is_set():
            if not self.inbox.empty():
                return True
            rung = self.outbox.rung()
            if rung:
                for channel in rung:
                    self._on_ring(channel.trainer, channel.group)
                return True
            os.sched_yield()
        return False

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
        pool = getattr(self, "_pool", None)
        if pool is not None:
            pool.shutdown()
            log.info("stepped several groups at once in %d pass(es)", self.parallel_passes)
        if hasattr(self, "outbox"):
            self.outbox.close()
        recorder = getattr(self, "recorder", None)
        if recorder is not None:
            recorder.close()
            self.recorder = None
        log.info("server %s stopped", self.name)

    def _next_timeout(self) -> float:
        deadlines = [g.deadline for g in self.arenas.groups.values() if g.deadline is not None]
        if not deadlines:
            return 1.0
        return min(max(min(deadlines) - time.monotonic(), 0.0), 1.0)

    def _handle(self, event: Event) -> None:
        try:
            if isinstance(event, QueryArrived):
                self._on_query(event.query, event.payload)
            elif isinstance(event, ActionsArrived):
                self._on_actions(event.key, event.payload)
            elif isinstance(event, ActionsRung):
                self._on_ring(event.trainer, event.group)
            elif isinstance(event, TrainerPresence):
                self._on_presence(event.key, event.present)
        except Exception:  # the loop must survive anything; a bug shows as a log line
            log.exception("unexpected error handling %s", type(event).__name__)

    # --- requests -------------------------------------------------------------------------------

    def _reply(self, query: zenoh.Query, message: Message) -> None:
        with query:
            query.reply(keys.server_request(self.name), codec.encode(message))

    def _on_query(self, query: zenoh.Query, payload: bytes) -> None:
        try:
            request: Message = codec.decode(payload, _REQUESTS)
            if isinstance(request, ErrorReply):
                raise errors.DecodeError(
                    "expected a request (status_request, open, join, reset, snapshot, "
                    "restore or close), got an error reply"
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
            self._require_alive(request.trainer)
            wanted = request.wanted_transports
            return self.arenas.open(request, lambda g, t: self._opened(g, t, wanted))
        if isinstance(request, JoinRequest):
            self._require_alive(request.trainer)
            return self.arenas.join(request, self._opened)
        if isinstance(request, ResetRequest):
            return self.arenas.group(request.group).reset(
                request.trainer, request.ticket, request.arenas, request.seeds
            )
        if isinstance(request, SnapshotRequest):
            return keep_state(self.arenas.group(request.group), request.trainer, request.ticket)
        if isinstance(request, RestoreRequest):
            group = self.arenas.group(request.group)
            return restore_state(group, request.trainer, request.ticket, request.state)
        if isinstance(request, CloseRequest):
            group = self.arenas.group(request.group)
            group.member(request.trainer, request.ticket)
            self._leave(group, request.trainer, "closed")
            return Ack(message=f"left group {request.group}")
        raise errors.DecodeError(f"not a request: {request.TYPE}")  # pragma: no cover

    def status(self) -> StatusReply:
        # The status request being answered has left the queue already.
        backlog = self.inbox.backlog()
        return StatusReply(
            server=self.name,
            package_version=_package_version(),
            max_arenas=self.config.max_arenas,
            arenas_used=self.arenas.used,
            step_deadline_s=self.config.step_deadline_s,
            uptime_s=time.monotonic() - self._started,
            groups=tuple(g.status() for g in self.arenas.groups.values()),
            queued_actions=backlog.queued_actions,
            queued_requests=backlog.queued_requests,
            dropped_frames=backlog.dropped_frames,
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

    def _opened(self, group: Group, trainer: str, transports: tuple[str, ...] = ()) -> Opened:
        self.outbox.open_for(trainer)
        member = group.members[trainer]
        offer = self.outbox.offer_channel(group, trainer, transports) if transports else None
        return Opened(
            server=self.name,
            group=group.group_id,
            arenas=tuple(group.arena_ids),
            ticket=member.ticket,
            spec=group.spec,
            steps=group.current_steps(trainer),
            server_minor=PROTOCOL_VERSION[1],
            offer=offer,
            shm=offer if isinstance(offer, ShmOffer) else None,  # what a 1.9 trainer reads
        )

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
        except errors.ProtocolError as error:
            self._refused(trainer, None, error)
            return
        if self._accept(trainer, actions):
            # Over Zenoh: whatever channel the trainer was offered, it does not take it.
            self.outbox.actions_over_zenoh(trainer, actions.group)

    def _on_ring(self, trainer: str, group: int) -> None:
        """``trainer`` put its Actions for ``group`` in its offered channel (a segment: rang)."""
        channel = self.outbox.offered_channel(trainer, group)
        if channel is None or not channel.rung():
            return  # the segment closed since (the trainer left), or the loop took them
        answer_s = time.perf_counter() - self._round_sent
        self._answer_s += ANSWER_AVERAGE_WEIGHT * (answer_s - self._answer_s)
        try:
            actions = channel.actions()
        except errors.ProtocolError as error:
            self._refused(trainer, group, error)
            return
        self._accept(trainer, actions)

    def _accept(self, trainer: str, actions: Actions) -> bool:
        """Hand ``actions`` to their group; whether it took them (a refusal is answered)."""
        try:
            self.arenas.group(actions.group).accept(actions, self.config.step_deadline_s)
            return True
        except errors.StaleActions as error:
            log.debug("dropped late actions from %s: %s", trainer, error)
        except errors.WrongTicket as error:
            # Not from the session that owns these agents: replying on the named trainer's
            # key would only disturb that trainer.
            log.warning("dropped actions in %s's name: %s", trainer, error)
        except errors.ProtocolError as error:
            self._refused(trainer, actions.group, error)
        return False

    def _refused(self, trainer: str, group: int | None, error: errors.ProtocolError) -> None:
        log.info("refused actions from %s: %s", trainer, error)
        if trainer not in self._alive_trainers:
            # Nobody of that name is connected: no reply to a key nobody reads. Each new
            # key a reply goes to costs Zenoh memory for good (bench/fuzz/fuzz_wire.py), so a
            # stranger inventing names must not make the server write to them.
            return
        self.outbox.send(trainer, ErrorReply(code=error.code, message=str(error), group=group))

    def _step_groups(self, groups: list[Group]) -> None:
        """Step ``groups``, several at once on the stepping threads, and deliver each group's
        round as its step is done. The loop takes no event until all are delivered, so
        nothing touches a group while a thread steps it."""
        if len(groups) == 1:
            self._step_group(groups[0], groups[0].step)
            self._round_sent = time.perf_counter()
            return
        if self._pool is None:
            self._pool = ThreadPoolExecutor(self.config.step_threads, "overtake-step")
        self.parallel_passes += 1
        stepping = [self._pool.submit(group.step) for group in groups]
        for group, future in zip(groups, stepping, strict=True):
            self._step_group(group, future.result)  # re-raises the step's failure here
        self._round_sent = time.perf_counter()

    def _step_group(self, group: Group, step: Callable[[], Mapping[str, Message]]) -> None:
        """Take ``group``'s round from ``step`` (its step, or a stepping thread's result),
        send each member its observations, publish and record it; a failure closes the
        group."""
        try:
            for trainer, message in step().items():
                self.outbox.send_steps(group, trainer, message)
            self.outbox.publish_world(group, time.monotonic())
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
                    self.outbox.send(trainer, reply)
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
                self.recorder.offer(group_world_frame(group, index, observations))
        except Exception:
            log.exception("could not record group %d's round %d", group.group_id, group.round)

    # --- trainers leaving ---------------------------------------------------------------------

    def _on_presence(self, key: str, present: bool) -> None:
        """A trainer's liveliness token came or went: one that went (died, or closed its
        session) leaves every group it was in, its cars off the road."""
        try:
            trainer = keys.parse_trainer_alive(key)
        except errors.ProtocolError:
            return
        if present:
            self._alive_trainers.add(trainer)
            return
        self._alive_trainers.discard(trainer)
        for group in list(self.arenas.groups.values()):
            if trainer in group.members:
                self._leave(group, trainer, "gone (liveliness token lost)")
        self.outbox.forget_trainer(trainer)

    def _leave(self, group: Group, trainer: str, why: str) -> None:
        self.outbox.forget_member(group.group_id, trainer)
        if self.arenas.leave(group, trainer, why):
            self.outbox.forget_group(group)
