"""How a trainer reaches simulator servers (:class:`RemoteConfig`: the endpoints, the
timeouts, the credentials, the transport of its rounds), and what it is told when it cannot."""

from __future__ import annotations

from dataclasses import dataclass, field

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
    steps_transport: Transport = "auto"
    """How rounds travel: ``auto`` through shared memory where the server is on this host (it
    offers a segment and this trainer can map it), over Zenoh otherwise; ``shm`` shared memory
    or a clear error; ``zenoh`` always over Zenoh (overtake.client.wire.steps_channel)."""
    spin_s: float = 0.002
    """Through shared memory, how long to wait for a round spinning (yielding the core at
    every look) before sleeping on the doorbell: a process that sleeps between rounds computes
    the next one slower on a virtual machine (overtake.ipc.doorbell). 0: always sleep."""

    @classmethod
    def from_connect(cls, connect: Endpoints | None) -> RemoteConfig:
        """Defaults, with ``connect`` (one endpoint or several; None: the default)."""
        return cls() if connect is None else cls(connect=endpoint_tuple(connect))

    def transport(self) -> TransportConfig:
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
    cause = connect_failure_cause(config.transport())
    return (
        f"could not connect to {', '.join(config.connect)} within "
        f"{config.connect_timeout_s:g} s ({zenoh_text}). "
        + (f"{cause[0].upper()}{cause[1:]}." if cause else likely_causes(config))
    )
