"""The trainer's side of the wire: a Zenoh connection and the arena groups opened through it.

:class:`Connection` is one Zenoh session with this trainer's liveliness token (the server frees
our arenas when it disappears) and the subscriber our observations arrive on.
:class:`ArenaGroup` is a set of arenas opened (or joined) in one request and stepped in lock
step; it survives a server restart by reopening its arenas and reporting the broken episodes
as truncated. :class:`~overtake.client.mlagents.environment.RemoteEnvironment` and the Gymnasium
environments are built on these two.

Which server serves an open request: the client asks every server on the network for its
status and picks the one with the most free arenas that can take the whole request (ties: the
fewest groups, then at random), unless ``server`` names one. A server that turns out full in
the meantime passes the request on to the next.
"""

from __future__ import annotations

import dataclasses
import logging
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from overtake.client.wire.connection import Connection
from overtake.client.wire.remote_config import RemoteConfig
from overtake.client.wire.steps_channel import offered, requested_transports
from overtake.protocol import errors
from overtake.protocol.messages import (
    Ack,
    Actions,
    BehaviourSpec,
    CloseRequest,
    GroupState,
    JoinRequest,
    Opened,
    OpenRequest,
    ResetRequest,
    RestoreRequest,
    SnapshotRequest,
    Steps,
)
from overtake.protocol.version import GROUP_STATE_SINCE_MINOR

__all__ = ["ArenaGroup", "Connection", "RemoteConfig"]

log = logging.getLogger("overtake.client")


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
    transport: str = "zenoh"
    """The transport this group's rounds take: ``zenoh``, or the channel the server offered
    (``shm``: its shared-memory segment with a doorbell, protocol 1.7)."""
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
            transports = requested_transports(conn.config.transport)
            # The 1.6 field too: a 1.9 server reads only that.
            request = dataclasses.replace(request, transports=transports, shm="shm" in transports)
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
        try:
            self.transport = conn.open_channel(self.server, self.group_id, offered(opened))
        except errors.ConnectError:
            self.close()  # a transport required and not offered: the arenas are not kept
            raise
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

    # --- a kept state (protocol 1.8): an exact resume of a remote run ------------------------

    @property
    def restorable(self) -> bool:
        """Whether the server keeps this group's state for us: a 1.8 server, and arenas we
        opened (alone in them; a joined arena is shared)."""
        return self.server_minor >= GROUP_STATE_SINCE_MINOR and isinstance(
            self.request, OpenRequest
        )

    def snapshot(self) -> dict[str, Any]:
        """The group's whole state between rounds, kept by the server for us as bytes (in a
        uint8 array, which a checkpoint stores): :meth:`restore` puts it back."""
        self._check_keepable("keep")
        if self._server_restarted():
            raise errors.ServerLost(f"server {self.server} restarted: group {self.group_id} gone")
        kept = self.connection.request(
            self.server,
            SnapshotRequest(
                trainer=self.connection.trainer, ticket=self.ticket, group=self.group_id
            ),
            GroupState,
        )
        return {"server_state": np.frombuffer(kept.state, dtype=np.uint8).copy()}

    def restore(self, snapshot: Mapping[str, Any]) -> None:
        """Put the group back as :meth:`snapshot` found it (this group or one opened the same
        way, on this server or another): the rounds after are those that followed it. A
        server refuses another configuration or size
        (:class:`~overtake.protocol.errors.BadConfig`)."""
        self._check_keepable("restore")
        kept = snapshot.get("server_state")
        if kept is None:
            raise ValueError(
                "not a remote group's state (no 'server_state'): an in-process snapshot "
                "cannot be put on a server"
            )
        steps = self.connection.request(
            self.server,
            RestoreRequest(
                trainer=self.connection.trainer,
                ticket=self.ticket,
                group=self.group_id,
                state=np.asarray(kept, dtype=np.uint8).tobytes(),
            ),
            Steps,
        )
        self.connection.track(self.server, self.group_id)  # earlier rounds' Steps are stale
        self._pending_restart = None
        self.round = steps.round
        self.last = steps

    def _check_keepable(self, verb: str) -> None:
        if self._in_flight:
            raise RuntimeError(
                f"group {self.group_id}: {verb} its state between rounds; receive the round "
                "in flight first"
            )
        if not self.restorable:
            raise TypeError(
                f"group {self.group_id} on server {self.server} cannot {verb} its state: it "
                f"needs a server of protocol 1.{GROUP_STATE_SINCE_MINOR} or later (this one is "
                f"1.{self.server_minor}) and arenas this trainer opened (not joined)"
            )

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
        # The last rows again, one round on: nothing earned or applied, and the episodes cut.
        truncated = dataclasses.replace(
            broken,
            round=broken.round + 1,
            reward=np.zeros_like(broken.reward),
            terminated=np.zeros_like(broken.terminated),
            # Agents that had just ended were reported already; the rest are cut short.
            truncated=~broken.ended,
            action_applied=np.full_like(broken.action_applied, -1),
            late=np.zeros_like(broken.late),
            reward_terms=np.zeros_like(broken.reward_terms),
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
                if conn.interrupted.is_set():
                    raise errors.Interrupted(
                        f"asked to stop while looking for a server to reopen "
                        f"{len(self.arena_ids)} arena(s) on ({error})"
                    ) from None
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
