"""``overtake-router``: a Zenoh router on the Python binding, for hosts without zenohd.

It does what the compose file's router service (zenohd, from the official eclipse/zenoh image)
does: it relays between simulator servers, trainers and spectators, and holds no overtake logic
beyond, with --isolate-trainers, the access control that keeps trainers apart
(``overtake.server.service.access``). It reads the same Zenoh JSON5 file
(``--config docker/zenoh-router.json5``); --listen, --connect and the credential and TLS
options override what the file says. Multicast scouting
and gossip are always off, as everywhere in overtake: every endpoint is explicit.

``python -m overtake.server.router`` is the same command. SIGINT or SIGTERM stops it cleanly.
"""

from __future__ import annotations

import json
import logging
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh

from overtake.cli import Command
from overtake.ipc.endpoints import check_endpoints
from overtake.ipc.transport import (
    DEFAULT_ENDPOINT,
    SecurityConfig,
    TransportConfig,
    warn_if_unconnected,
    warn_if_unguarded,
)
from overtake.protocol import errors

from .errors import StartError
from .service.access import isolation_rules, users_in

log = logging.getLogger("overtake.router")


@dataclass(frozen=True)
class RouterConfig:
    """A Zenoh router, for hosts without zenohd (the overtake-router command)."""

    config: Path | None = None
    """a Zenoh JSON5 configuration file, e.g. docker/zenoh-router.json5 (zenohd reads the same
    file); the options below override it"""
    listen: tuple[str, ...] = ()
    """endpoints to listen on (default: the file's, else tcp/127.0.0.1:7447, loopback only);
    tcp/0.0.0.0:7447 or tls/0.0.0.0:7447 lets other hosts in"""
    connect: tuple[str, ...] = ()
    """other Zenoh routers to connect to (default: the file's)"""
    security: SecurityConfig = field(default_factory=SecurityConfig)
    """usrpwd (--credentials-file: the users it admits) and TLS (--tls-certificate and
    --tls-private-key for tls/ endpoints; --tls-mtls with --tls-root-ca to check clients')"""
    isolate_trainers: bool = False
    """Zenoh access control (needs usrpwd): each trainer user reaches only its own arenas'
    steps and actions, and no world frames; --server-users may serve, --spectator-users may
    watch; every other user of the credentials is a trainer (overtake.server.service.access)"""
    server_users: tuple[str, ...] = ()
    """with --isolate-trainers: the users overtake-server runs as"""
    spectator_users: tuple[str, ...] = ()
    """with --isolate-trainers: the users that may watch every arena (overtake-spectate)"""
    log_level: str = "info"
    """the lowest level of log lines shown: debug, info, warning or error"""


def _endpoints(conf: zenoh.Config, key: str) -> tuple[str, ...]:
    """The file's endpoints under ``key`` (a list, or a list per mode)."""
    value = json.loads(conf.get_json(key))
    if isinstance(value, dict):
        value = value.get("router") or []
    return tuple(value or ())


def zenoh_config(config: RouterConfig) -> tuple[zenoh.Config, TransportConfig]:
    """The router's Zenoh configuration, and the endpoints and security it ends up with."""
    if config.config is not None:
        try:
            conf = zenoh.Config.from_file(str(config.config))
        except (zenoh.ZError, OSError, ValueError) as error:
            raise errors.ConnectError(f"--config {config.config}: {error}") from None
        mode = json.loads(conf.get_json("mode"))
        if mode not in (None, "router"):
            raise errors.ConnectError(
                f"--config {config.config} says mode {mode!r}; overtake-router runs a router"
            )
    else:
        conf = zenoh.Config()
    conf.insert_json5("mode", '"router"')
    # Zenoh's shared memory is off in every overtake process (TransportConfig's
    # zenoh_shared_memory says why): a router with it on made a segment at start that a
    # SIGKILL left in /dev/shm for good, and relayed nothing through it.
    conf.insert_json5("transport/shared_memory/enabled", "false")
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("scouting/gossip/enabled", "false")
    listen = config.listen or _endpoints(conf, "listen/endpoints") or (DEFAULT_ENDPOINT,)
    connect = config.connect or _endpoints(conf, "connect/endpoints")
    check_endpoints("--listen", listen)
    check_endpoints("--connect", connect)
    conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    # A file may carry its own TLS identity; then a tls/ listener needs no --tls-certificate.
    file_has_identity = json.loads(conf.get_json("transport/link/tls/listen_certificate"))
    config.security.check(() if file_has_identity else listen, connect)
    for key, value in config.security.zenoh_settings():
        conf.insert_json5(key, value)
    if config.isolate_trainers:
        conf.insert_json5("access_control", json.dumps(isolation_for(config, conf)))
    elif config.server_users or config.spectator_users:
        raise errors.ConnectError("--server-users and --spectator-users need --isolate-trainers")
    return conf, TransportConfig(
        mode="router", listen=listen, connect=connect, security=config.security
    )


def isolation_for(config: RouterConfig, conf: zenoh.Config) -> dict[str, Any]:
    """The access control --isolate-trainers asks for, from the users of the credentials."""
    path = credentials_path(config, conf)
    if path is None:
        raise errors.ConnectError(
            "--isolate-trainers tells users apart by their usrpwd names: give "
            "--credentials-file (the user:password lines the router admits)"
        )
    try:
        users = users_in(path.read_text())
    except OSError as error:
        raise errors.ConnectError(f"cannot read the credentials {path}: {error}") from None
    unknown = [u for u in (*config.server_users, *config.spectator_users) if u not in users]
    if unknown:
        raise errors.ConnectError(
            f"--server-users / --spectator-users {unknown} are not in {path} (it lists {users})"
        )
    roles = {*config.server_users, *config.spectator_users}
    try:
        return isolation_rules(
            config.server_users, config.spectator_users, [u for u in users if u not in roles]
        )
    except ValueError as error:
        raise errors.ConnectError(f"--isolate-trainers: {error}") from None


def credentials_path(config: RouterConfig, conf: zenoh.Config) -> Path | None:
    """The users the router admits: --credentials-file, or the
    ``transport/auth/usrpwd/dictionary_file`` of the --config file; None: no usrpwd check."""
    if config.security.credentials_file is not None:
        return config.security.credentials_file
    dictionary = json.loads(conf.get_json("transport/auth/usrpwd/dictionary_file"))
    return Path(dictionary) if dictionary else None


def usrpwd_source(config: RouterConfig, conf: zenoh.Config) -> str | None:
    """Where the users the router admits come from, in words (None: no usrpwd check)."""
    path = credentials_path(config, conf)
    if path is None:
        return None
    if config.security.credentials_file is not None:
        return f"--credentials-file {path}"
    return f"dictionary_file {path} of --config {config.config}"


def log_start(
    zid: object, config: RouterConfig, conf: zenoh.Config, transport: TransportConfig
) -> None:
    """The start line (endpoints and who is admitted), and a warning for listeners anyone who
    reaches them may use."""
    source = usrpwd_source(config, conf)
    mtls = bool(json.loads(conf.get_json("transport/link/tls/enable_mtls")))
    auth = f"usrpwd: the users of {source}" if source else "no usrpwd check"
    if mtls:
        auth += "; mutual TLS"
    acl = json.loads(conf.get_json("access_control"))
    if config.isolate_trainers:
        trainers = [s["usernames"][0] for s in acl["subjects"] if s["id"].startswith("trainer ")]
        auth += (
            f"; trainers isolated: servers {list(config.server_users)}, spectators "
            f"{list(config.spectator_users)}, trainers {trainers}"
        )
    elif acl.get("enabled"):
        auth += f"; the access control of --config {config.config}"
    log.info("router %s listening on %s (%s)", zid, ", ".join(transport.listen), auth)
    warn_if_unguarded(transport, log, usrpwd=source is not None, mtls=mtls)


def main(config: RouterConfig, stop: threading.Event | None = None) -> None:
    """Route until ``stop`` is set (the command: until SIGINT or SIGTERM)."""
    logging.basicConfig(
        level=config.log_level.upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s"
    )
    zenoh.init_log_from_env_or("error")
    stop = stop or threading.Event()
    conf, transport = zenoh_config(config)
    try:
        session = zenoh.open(conf)
    except zenoh.ZError as error:
        raise StartError(
            f"could not start ({transport.describe()}): "
            f"{str(error).split(' at /')[0]}. Is the port in use, or the address "
            "not one of this host's?"
        ) from None
    try:
        log_start(session.zid(), config, conf, transport)
        warn_if_unconnected(session, transport, log)
        while not stop.wait(1.0):  # woken each second so the signal handlers run promptly
            pass
    finally:
        session.close()
        log.info("router stopped")


def _say_stopping(name: str) -> None:
    log.info("received %s, shutting down", name)


COMMAND = Command("overtake-router", RouterConfig, main, stopping="event", on_stop=_say_stopping)


if __name__ == "__main__":
    COMMAND.run()
