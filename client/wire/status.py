"""``overtake-status``: what every simulator server on the network is doing."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field

from overtake.cli import Command
from overtake.client.wire.connection import Connection
from overtake.client.wire.remote_config import RemoteConfig
from overtake.ipc.transport import DEFAULT_ENDPOINT, SecurityConfig
from overtake.protocol.messages import StatusReply


@dataclass(frozen=True)
class StatusConfig:
    """The simulator servers on the network, their arenas and their rates."""

    connect: tuple[str, ...] = (DEFAULT_ENDPOINT,)
    """Zenoh endpoints: a server's --listen address or a router's."""
    timeout_s: float = 3.0
    """How long to wait for the network (the router or server at --connect) and then for the
    servers to answer."""
    json: bool = False
    """Print the replies as JSON instead of a table."""
    server: str | None = None
    """Only this server (its --name). The exit status is 1 when no server (or not this one)
    answers, so the command serves as a health check."""
    security: SecurityConfig = field(default_factory=SecurityConfig)
    """usrpwd credentials and TLS certificates"""


def format_status(statuses: list[StatusReply]) -> str:
    lines = []
    for s in sorted(statuses, key=lambda s: s.server):
        lines.append(
            f"{s.server}: {s.arenas_used}/{s.max_arenas} arenas, {len(s.groups)} "
            f"group(s), step deadline {s.step_deadline_s:g} s, up {s.uptime_s:.0f} s, "
            f"overtake {s.package_version}"
        )
        lines.append(
            f"  queued: {s.queued_actions} actions, {s.queued_requests} requests; "
            f"{s.dropped_frames} frames dropped at the queues' bounds"
        )
        for g in s.groups:
            lines.append(
                f"  group {g.group}: {g.preset}, arenas {list(g.arenas)}, "
                f"{g.agents_per_arena} agent(s) each, trainers {list(g.trainers)}, "
                f"{g.rounds} rounds, {g.rounds_per_s:.1f} rounds/s, "
                f"{g.agent_steps_per_s:.0f} agent-steps/s, {g.late_agents} late"
            )
    return "\n".join(lines) if lines else "no overtake server answered"


def main(config: StatusConfig) -> list[StatusReply]:
    connection = Connection(
        RemoteConfig(
            connect=config.connect,
            connect_timeout_s=config.timeout_s,
            request_timeout_s=config.timeout_s,
            security=config.security,
        )
    )
    try:
        statuses = connection.discover()
    finally:
        connection.close()
    if config.server is not None:
        statuses = [s for s in statuses if s.server == config.server]
    if config.json:
        print(json.dumps([asdict(s) for s in statuses], default=list, indent=2))
    elif config.server is not None and not statuses:
        print(f"server {config.server!r} did not answer")
    else:
        print(format_status(statuses))
    return statuses


def _report(_config: StatusConfig, replies: list[StatusReply]) -> int:
    return 0 if replies else 1  # no server answered


COMMAND = Command("overtake-status", StatusConfig, main, report=_report)


if __name__ == "__main__":
    COMMAND.run()
