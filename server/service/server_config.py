"""The server's configuration: what ``overtake-server``'s flags set."""

from __future__ import annotations

import os
import socket
from dataclasses import dataclass, field

from overtake.cli import Output
from overtake.ipc.transport import DEFAULT_ENDPOINT, SecurityConfig, TransportConfig
from overtake.viz.recording import RecordingConfig

from ..channels import OFFERED, ChannelMaker
from .recorder import default_rrd

# With its sink on, a server logs every arena one round in this many: logging every round
# costs trainers 20-30% of their steps per second, one in ten a few per cent (bench/RESULTS.md).
SERVER_RECORD_EVERY = 10


def default_server_name() -> str:
    host = "".join(c if c.isalnum() or c in "-_." else "-" for c in socket.gethostname())
    return f"sim-{host[:40] or 'host'}-{os.getpid()}"


@dataclass(frozen=True)
class ServerConfig:
    """The highway simulator, served to trainers over Zenoh (the overtake-server command)."""

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
    step_threads: int = 1
    """Groups stepped at once, each on its own thread (the simulation's compiled loops release
    the GIL), when several are ready: for a server with cores to spare beside its trainers.
    1 steps one group at a time."""
    shared_memory: bool = True
    """Offer a trainer that asks (one on this host, --transport auto or shm) a shared-memory
    channel for its rounds; --no-shared-memory sends every round over Zenoh."""
    spin_s: float = 0.002
    """With trainers on the shared-memory channel, how long the loop waits for their next
    Actions spinning (yielding the core at every look) before it sleeps: a process that sleeps
    between rounds computes the next one slower on a virtual machine
    (overtake.ipc.doorbell). 0: always sleep."""
    lease_s: float = 3.0
    """Trainers notice within this that this server's host vanished (a trainer's own lease,
    RemoteConfig.lease_s, bounds how soon its arenas are freed when its host vanishes)."""
    security: SecurityConfig = field(default_factory=SecurityConfig)
    """usrpwd credentials (when connecting to a router that asks for them, and the users this
    server admits) and TLS certificates (for tls/ endpoints)"""
    log_level: str = "info"
    """the lowest level of log lines shown: debug, info, warning or error"""
    recording: RecordingConfig = field(
        default_factory=lambda: RecordingConfig(sink="off", record_every=SERVER_RECORD_EVERY)
    )
    """Rerun: this server logs every arena it steps itself (default off; spectators watch
    without it), one round in --record-every. With --sink file the .rrd defaults to
    runs/server/<name>.rrd."""

    def offered_channels(self) -> dict[str, ChannelMaker]:
        """The channels besides Zenoh this server offers trainers that ask, by transport."""
        return {t: make for t, make in OFFERED.items() if t != "shm" or self.shared_memory}

    def session_config(self) -> TransportConfig:
        return TransportConfig(
            mode="peer",
            listen=self.listen,
            connect=self.connect,
            lease_s=self.lease_s,
            security=self.security,
        )

    def output_paths(self) -> tuple[Output, ...]:
        """What this command writes (checked before the server starts)."""
        return (self.recording.output(default_rrd(self.name)),)
