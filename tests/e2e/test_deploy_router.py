"""Deployment: the router's configuration file, what the router and a server say about whom
they admit (and warn when anyone may), the security options' checks, and a router that
leaves nothing in /dev/shm however it ends.

Every process is real (``python -m ...`` of the installed commands) on 127.0.0.1 with free
ports; each is ended by its PID, and every wait is on a condition with a deadline
(``tests.support.remote.wait_until``), never a fixed sleep.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import pytest
import zenoh

from overtake.ipc.transport import (
    PASSWORD_ENV,
    USER_ENV,
    SecurityConfig,
    TransportConfig,
    unguarded_listeners,
    warn_if_unguarded,
)
from overtake.protocol import errors
from overtake.server.router import RouterConfig, log_start, zenoh_config

from tests.support.deploy import LOOPBACK, ROOT, start_router
from tests.support.remote import free_port, wait_until

# Credentials in the developer's environment must not leak into these tests.
pytestmark = pytest.mark.usefixtures("no_inherited_credentials")


def test_router_file_is_accepted_by_the_python_binding():
    conf, transport = zenoh_config(RouterConfig(config=ROOT / "docker" / "zenoh-router.json5"))
    assert transport.listen == ("tcp/0.0.0.0:7447",)
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert json.loads(conf.get_json("scouting/gossip/enabled")) is False
    # The command line's --listen replaces the file's.
    conf, transport = zenoh_config(
        RouterConfig(config=ROOT / "docker" / "zenoh-router.json5", listen=("tcp/127.0.0.1:7000",))
    )
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7000"]


def test_listeners_anyone_may_use_are_found():
    anyone = ("tcp/0.0.0.0:7447", "tcp/[::]:7447", "tls/192.0.2.10:7447", "udp/sim.lan:7447")
    local = (
        "tcp/127.0.0.1:7447",
        "tcp/127.1.2.3:1",
        "tcp/[::1]:7447",
        "tls/localhost:7447",
        "unixsock-stream//tmp/zenoh.sock",
    )
    assert unguarded_listeners(anyone + local, usrpwd=False, mtls=False) == anyone
    assert unguarded_listeners(anyone, usrpwd=True, mtls=False) == ()
    # Mutual TLS guards TLS links only; a tcp/ listener beside them stays open.
    assert unguarded_listeners(anyone, usrpwd=False, mtls=True) == (
        "tcp/0.0.0.0:7447",
        "tcp/[::]:7447",
        "udp/sim.lan:7447",
    )


def test_server_warns_when_anyone_who_reaches_it_may_use_it(tmp_path: Path, caplog):
    from overtake.server.service.server import ServerConfig

    log = logging.getLogger("test.unguarded")
    credentials = tmp_path / "credentials.txt"
    credentials.write_text("trainer:secret\n")

    def warnings(config: TransportConfig) -> list[str]:
        caplog.clear()
        warn_if_unguarded(config, log)
        return [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]

    caplog.set_level(logging.INFO, logger=log.name)
    (warning,) = warnings(ServerConfig(listen=("tcp/0.0.0.0:7447",)).session_config())
    assert "tcp/0.0.0.0:7447" in warning and "anyone who reaches" in warning
    assert "--credentials-file" in warning and "--tls-mtls" in warning
    assert (
        warnings(
            ServerConfig(
                listen=("tcp/0.0.0.0:7447",), security=SecurityConfig(credentials_file=credentials)
            ).session_config()
        )
        == []
    )
    assert warnings(ServerConfig().session_config()) == []  # loopback, the default
    assert warnings(ServerConfig(listen=()).session_config()) == []


def test_router_says_whom_it_admits_and_warns_when_anyone_may(tmp_path: Path, caplog):
    credentials = tmp_path / "credentials.txt"
    credentials.write_text("trainer:secret\n")
    guarded_file = tmp_path / "router.json5"
    guarded_file.write_text(
        '{ mode: "router", listen: { endpoints: ["tcp/0.0.0.0:7447"] }, '
        f"transport: {{ auth: {{ usrpwd: {{ dictionary_file: "
        f"{json.dumps(str(credentials))} }} }} }} }}"
    )

    def start_lines(config: RouterConfig) -> tuple[str, list[str]]:
        caplog.clear()
        conf, transport = zenoh_config(config)
        log_start("zid", config, conf, transport)
        info = [r.getMessage() for r in caplog.records if r.levelno == logging.INFO]
        return info[0], [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]

    caplog.set_level(logging.INFO, logger="overtake.router")
    # The compose file's router settings: every interface, nobody checked.
    started, warned = start_lines(RouterConfig(config=ROOT / "docker" / "zenoh-router.json5"))
    assert "tcp/0.0.0.0:7447" in started and "no usrpwd check" in started
    assert len(warned) == 1 and "anyone who reaches" in warned[0]
    # usrpwd from the file's dictionary_file: said so, and no warning.
    started, warned = start_lines(RouterConfig(config=guarded_file))
    assert f"dictionary_file {credentials} of --config {guarded_file}" in started, started
    assert "no usrpwd" not in started and warned == []
    # ... or from --credentials-file.
    started, warned = start_lines(
        RouterConfig(
            listen=("tcp/0.0.0.0:7447",), security=SecurityConfig(credentials_file=credentials)
        )
    )
    assert f"--credentials-file {credentials}" in started and warned == []
    # Loopback only: nobody else reaches it.
    started, warned = start_lines(RouterConfig(listen=("tcp/127.0.0.1:7447",)))
    assert "no usrpwd check" in started and warned == []


def test_security_options_are_refused_with_the_option_named(tmp_path: Path, monkeypatch):
    with pytest.raises(errors.ConnectError, match="--tls-root-ca .*no such file"):
        SecurityConfig(tls_root_ca=tmp_path / "missing.pem").check((), ("tls/h:1",))
    with pytest.raises(errors.ConnectError, match="needs this side's certificate"):
        SecurityConfig().check(("tls/127.0.0.1:1",), ())
    with pytest.raises(errors.ConnectError, match="has no password"):
        SecurityConfig(user="alice").usrpwd()
    secret = tmp_path / "pw"
    secret.write_text("from-file\n")
    assert SecurityConfig(user="alice", password_file=secret).usrpwd() == ("alice", "from-file")
    monkeypatch.setenv(USER_ENV, "bob")
    monkeypatch.setenv(PASSWORD_ENV, "from-env")
    assert SecurityConfig().usrpwd() == ("bob", "from-env")
    # A client has nobody to admit: the listener's option is refused, saying what to use.
    credentials = tmp_path / "credentials.txt"
    credentials.write_text("alice:secret\n")
    with pytest.raises(
        errors.ConnectError, match="only connects.*--user NAME with --password-file"
    ):
        TransportConfig(
            mode="client",
            connect=("tcp/127.0.0.1:1",),
            security=SecurityConfig(credentials_file=credentials),
        ).zenoh_config()
    TransportConfig(
        mode="peer",
        listen=("tcp/127.0.0.1:1",),
        security=SecurityConfig(credentials_file=credentials),
    ).zenoh_config()
    # The password never sits in a configuration (they are written to run.json and checkpoints).
    assert "password" not in {f for f in SecurityConfig.__dataclass_fields__}


@pytest.mark.timeout(60)
@pytest.mark.parametrize("ending", ["SIGTERM", "SIGKILL"])
def test_a_router_leaves_nothing_in_dev_shm_however_it_ends(background, ending):
    """overtake-router with the deployment's file keeps Zenoh's shared memory off, as every
    overtake process does: with it on, the router made a ``<number>.zenoh`` segment at start,
    and SIGKILL left it in /dev/shm for good (found by the fault matrix, issue 47)."""
    import signal as signals

    from overtake.ipc.shared_memory import shm_dir

    def zenoh_segments() -> set[str]:
        return {p.name for p in shm_dir().glob("*.zenoh")}

    before = zenoh_segments()
    endpoint = f"tcp/{LOOPBACK}:{free_port()}"
    router = start_router(background, "router", [endpoint])
    # A peer's traffic through it, as a server's and a trainer's.
    session = zenoh.open(TransportConfig(mode="client", connect=(endpoint,)).zenoh_config())
    try:
        got: list[int] = []
        subscriber = session.declare_subscriber("shm-test/x", lambda s: got.append(len(s.payload)))
        publisher = session.declare_publisher("shm-test/x")
        wait_until(lambda: publisher.put(b"x" * 200_000) or bool(got), 10.0, "a put through it")
        subscriber.undeclare()
    finally:
        session.close()
    router.proc.send_signal(getattr(signals, ending))
    router.proc.wait(30)
    assert zenoh_segments() <= before
