"""Zenoh session settings shared by servers, trainers and spectators.

Always explicit endpoints and never multicast scouting (the default scouts on 224.0.0.224 and
listens on every interface). The lease bounds how long a vanished host's liveliness tokens
survive: a trainer whose machine drops off the network frees its arenas within it.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Literal

import zenoh

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"


@dataclass(frozen=True)
class TransportConfig:
    """How this process joins the Zenoh network."""

    mode: Literal["peer", "client", "router"] = "client"
    listen: tuple[str, ...] = ()
    """Endpoints to listen on, e.g. ``tcp/127.0.0.1:7447`` (``tcp/0.0.0.0:7447``: all hosts)."""
    connect: tuple[str, ...] = ()
    """Endpoints (a router, or a listening server) to connect to."""
    connect_timeout_s: float = 5.0
    """How long opening the session keeps retrying ``connect`` before giving up."""
    lease_s: float = 3.0
    """The lease this side announces: if it falls silent (its host vanished, or it froze),
    its peers declare it gone after this long, and its liveliness tokens vanish."""
    user: str | None = None
    """Zenoh usrpwd authentication: this side's user name (with ``password``)."""
    password: str | None = None
    credentials_file: str | None = None
    """A listening side's ``user:password`` lines it accepts (usrpwd authentication)."""
    extra_json5: tuple[tuple[str, str], ...] = field(default=())
    """More Zenoh settings as (key, JSON5 value) pairs, e.g. TLS certificates."""

    def zenoh_config(self) -> zenoh.Config:
        conf = zenoh.Config()
        conf.insert_json5("mode", json.dumps(self.mode))
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("scouting/gossip/enabled", "false")
        conf.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        conf.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
        if self.connect:
            timeout_ms = max(int(self.connect_timeout_s * 1000), 0)
            conf.insert_json5("connect/timeout_ms", str(timeout_ms))
            conf.insert_json5("connect/retry", "{ period_init_ms: 100, period_max_ms: 1000, "
                                               "period_increase_factor: 2 }")
            if self.mode != "client":
                # Peers and routers must not fail to start when the other side is not up yet.
                conf.insert_json5("connect/exit_on_failure", "false")
        lease_ms = max(int(self.lease_s * 1000), 200)
        conf.insert_json5("transport/link/tx/lease", str(lease_ms))
        conf.insert_json5("transport/link/tx/keep_alive", "4")
        if self.user is not None or self.credentials_file is not None:
            auth: dict[str, str] = {}
            if self.user is not None:
                auth["user"] = self.user
                auth["password"] = self.password or ""
            if self.credentials_file is not None:
                auth["dictionary_file"] = self.credentials_file
            conf.insert_json5("transport/auth/usrpwd", json.dumps(auth))
        for key, value in self.extra_json5:
            conf.insert_json5(key, value)
        return conf

    def describe(self) -> str:
        parts = [self.mode]
        if self.listen:
            parts.append("listening on " + ", ".join(self.listen))
        if self.connect:
            parts.append("connecting to " + ", ".join(self.connect))
        return " ".join(parts)


def open_session(config: TransportConfig) -> zenoh.Session:
    """A Zenoh session; raises ``zenoh.ZError`` as Zenoh does (callers add the likely causes)."""
    return zenoh.open(config.zenoh_config())
