"""How a trainer reaches simulator servers (:class:`RemoteConfig`: the endpoints, the
timeouts, the credentials, the transport of its rounds), and what it is told when it cannot."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated

import tyro

from overtake.cli.options import unset
from overtake.client.wire.steps_channel import Transport
from overtake.ipc.transport import (
    DEFAULT_ENDPOINT,
    Endpoints,
    SecurityConfig,
    TransportConfig,
    connect_failure_cause,
    endpoint_tuple,
)


@dataclass(frozen=True)
class RemoteConfig:
    """How a trainer reaches simulator servers. A command's :class:`Where` holds one: its
    fields are the commands' flags (``--server``, ``--transport``, the timeouts, the security
    options), all but ``connect``, which the command's own ``--connect`` gives."""

    # Suppressed on the command line: Where's --connect says where (none: this process).
    connect: Annotated[tuple[str, ...], tyro.conf.Suppress] = (DEFAULT_ENDPOINT,)
    """Zenoh endpoints: a server's ``--listen`` address or a router's (one or more: the first
    reachable is used)."""
    server: Annotated[str | None, unset("NAME")] = None
    """with --connect: open the arenas on this server (its --name); unset: the least loaded"""
    connect_timeout_s: float = 5.0
    """with --connect: how long to keep trying to reach the endpoints before failing with
    ConnectError"""
    request_timeout_s: float = 10.0
    """with --connect: how long an open, reset, close or status request may take"""
    step_timeout_s: float = 120.0
    """with --connect: how long to wait for a step's observations (longer than the server's
    step deadline)"""
    reconnect_timeout_s: float = 30.0
    """with --connect: after losing the server, how long to wait for one to reopen the arenas
    on (0: never)"""
    lease_s: float = 3.0
    """with --connect: if this process's host vanishes (or it freezes), servers free its
    arenas within this"""
    security: SecurityConfig = field(default_factory=SecurityConfig)
    """usrpwd credentials and TLS certificates for --connect (the password from a file or the
    environment)"""
    trainer_name: Annotated[str | None, unset("NAME")] = None
    """with --connect: a readable prefix for this process's id in server logs and status;
    unset: the usrpwd user, else trainer. A router that isolates trainers (overtake-router
    --isolate-trainers) lets a user's session use only ids that begin with its user name."""
    transport: Transport = "auto"
    """how a server's rounds reach this process (--connect): auto (shared memory where the
    server is on this host, offers a segment and this process can map it; Zenoh otherwise),
    shm (shared memory or an error), zenoh"""
    spin_s: float = 0.002
    """through shared memory, how long to wait for a round spinning (yielding the core at
    every look) before sleeping on the doorbell: a process that sleeps between rounds computes
    the next one slower on a virtual machine (overtake.ipc.doorbell); 0 always sleeps"""

    @classmethod
    def from_connect(cls, connect: Endpoints | None) -> RemoteConfig:
        """Defaults, with ``connect`` (one endpoint or several; None: the default)."""
        return cls() if connect is None else cls(connect=endpoint_tuple(connect))

    def session_config(self) -> TransportConfig:
        return TransportConfig(
            mode="client",
            connect=self.connect,
            connect_timeout_s=self.connect_timeout_s,
            lease_s=self.lease_s,
            security=self.security,
        )


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
    cause = connect_failure_cause(config.session_config())
    return (
        f"could not connect to {', '.join(config.connect)} within "
        f"{config.connect_timeout_s:g} s ({zenoh_text}). "
        + (f"{cause[0].upper()}{cause[1:]}." if cause else likely_causes(config))
    )
