"""Zenoh session settings shared by servers, routers, trainers and spectators.

Always explicit endpoints and never multicast scouting (the default scouts on 224.0.0.224 and
listens on every interface). The lease bounds how long a vanished host's liveliness tokens
survive: a trainer whose machine drops off the network frees its arenas within it.

Links are secured the same way by every command (:class:`SecurityConfig`): Zenoh's usrpwd
authentication (a listening side with a credentials file admits only the users it lists) and
TLS (``tls/HOST:PORT`` endpoints; the connecting side checks the listener's certificate against
a CA, and with mutual TLS the listener checks the connecting side's too). Passwords come from a
file or the environment, never from the command line: a command line is visible to every user
of the host, and the configurations are recorded in run directories and checkpoints.
"""

from __future__ import annotations

import ipaddress
import json
import logging
import os
import socket
import ssl
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, TypeVar

import zenoh

from overtake.protocol.errors import ConnectError

from .endpoints import check_endpoints, host_port, protocol_of

T = TypeVar("T")

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"

Endpoints = str | Sequence[str]
"""Where to reach Zenoh, as every face and configuration takes it: one endpoint, or several
(the first reachable is used); :func:`endpoint_tuple` makes it the tuple configurations hold."""


def endpoint_tuple(connect: Endpoints) -> tuple[str, ...]:
    """``connect`` as a tuple of endpoints (one endpoint's string is not its characters)."""
    return (connect,) if isinstance(connect, str) else tuple(connect)


USER_ENV = "OVERTAKE_ZENOH_USER"
"""The usrpwd user name when ``--user`` is not given."""
PASSWORD_ENV = "OVERTAKE_ZENOH_PASSWORD"
"""The usrpwd password when ``--password-file`` is not given."""


@dataclass(frozen=True)
class SecurityConfig:
    """Who this process says it is on Zenoh links, and whom it trusts (usrpwd and TLS)."""

    user: str | None = None
    """usrpwd: the user name this process presents when it connects (default:
    $OVERTAKE_ZENOH_USER); its password comes from --password-file or $OVERTAKE_ZENOH_PASSWORD"""
    password_file: Path | None = None
    """usrpwd: a file whose first line is the password (default: $OVERTAKE_ZENOH_PASSWORD)"""
    credentials_file: Path | None = None
    """usrpwd, listening side (router, server): the user:password lines it admits, one a line;
    without it anyone who reaches the port may connect"""
    tls_root_ca: Path | None = None
    """TLS: the PEM certificate of the CA that signed the certificates this process trusts (the
    router's; with --tls-mtls also the connecting sides')"""
    tls_certificate: Path | None = None
    """TLS: this process's own PEM certificate (a listener's, or a client's with --tls-mtls)"""
    tls_private_key: Path | None = None
    """TLS: the PEM private key of --tls-certificate"""
    tls_mtls: bool = False
    """TLS: mutual authentication; a listener admits only clients with a certificate signed by
    --tls-root-ca, and a client presents --tls-certificate"""
    tls_verify_name: bool = True
    """TLS: check that the router's certificate names the host or address connected to"""

    def user_name(self) -> str | None:
        """The usrpwd user this process presents: --user, else $OVERTAKE_ZENOH_USER."""
        return self.user or os.environ.get(USER_ENV) or None

    def usrpwd(self) -> tuple[str, str] | None:
        """The (user, password) to present, or None; reads the password file or environment."""
        user = self.user_name()
        if user is None:
            if self.password_file is not None:
                raise ConnectError(
                    f"--password-file {self.password_file} is given without a "
                    f"user: add --user NAME (or set ${USER_ENV})"
                )
            return None  # a password in the environment alone names nobody: no usrpwd
        if self.password_file is not None:
            try:
                text = Path(self.password_file).read_text(encoding="utf-8")
            except OSError as error:
                raise ConnectError(
                    f"--password-file {self.password_file}: cannot read it ({error.strerror})"
                ) from None
            password = text.splitlines()[0] if text.strip() else ""
            where = f"--password-file {self.password_file}"
        else:
            password = os.environ.get(PASSWORD_ENV, "")
            where = f"${PASSWORD_ENV}"
        if not password:
            raise ConnectError(
                f"user {user!r} has no password: {where} is empty or unset "
                f"(give --password-file PATH, or set ${PASSWORD_ENV})"
            )
        return user, password

    def check(self, listen: tuple[str, ...], connect: tuple[str, ...]) -> None:
        """Refuse, naming the option, a setting Zenoh would fail on later with a vaguer error."""
        for flag, path in (
            ("--password-file", self.password_file),
            ("--credentials-file", self.credentials_file),
            ("--tls-root-ca", self.tls_root_ca),
            ("--tls-certificate", self.tls_certificate),
            ("--tls-private-key", self.tls_private_key),
        ):
            if path is not None and not Path(path).is_file():
                raise ConnectError(f"{flag} {path}: no such file")
        if (self.tls_certificate is None) != (self.tls_private_key is None):
            raise ConnectError("--tls-certificate and --tls-private-key go together")
        tls_listen = [e for e in listen if protocol_of(e) == "tls"]
        if tls_listen and self.tls_certificate is None:
            raise ConnectError(
                f"listening on {', '.join(tls_listen)} needs this side's "
                "certificate: give --tls-certificate and --tls-private-key"
            )
        if self.tls_mtls and self.tls_root_ca is None:
            raise ConnectError(
                "--tls-mtls needs --tls-root-ca, the CA that signed the other side's certificate"
            )
        if (
            self.tls_mtls
            and self.tls_certificate is None
            and any(protocol_of(e) == "tls" for e in connect)
        ):
            raise ConnectError(
                "--tls-mtls needs this side's certificate: give "
                "--tls-certificate and --tls-private-key"
            )

    def zenoh_settings(self) -> list[tuple[str, str]]:
        """(key, JSON5 value) pairs for a Zenoh configuration; only what is set."""
        settings: list[tuple[str, str]] = []
        auth: dict[str, str] = {}
        credentials = self.usrpwd()
        if credentials is not None:
            auth["user"], auth["password"] = credentials
        if self.credentials_file is not None:
            auth["dictionary_file"] = str(self.credentials_file)
        if auth:
            settings.append(("transport/auth/usrpwd", json.dumps(auth)))
        tls: dict[str, object] = {}
        if self.tls_root_ca is not None:
            tls["root_ca_certificate"] = str(self.tls_root_ca)
        if self.tls_certificate is not None and self.tls_private_key is not None:
            # One identity for both roles: a server listens and connects with the same one.
            tls["listen_certificate"] = tls["connect_certificate"] = str(self.tls_certificate)
            tls["listen_private_key"] = tls["connect_private_key"] = str(self.tls_private_key)
        if self.tls_mtls:
            tls["enable_mtls"] = True
        if not self.tls_verify_name:
            tls["verify_name_on_connect"] = False
        for key, value in tls.items():
            settings.append((f"transport/link/tls/{key}", json.dumps(value)))
        return settings


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
    security: SecurityConfig = field(default_factory=SecurityConfig)
    """usrpwd credentials and TLS certificates."""
    zenoh_shared_memory: bool = False
    """Zenoh's own shared-memory transport (on by default in Zenoh 1.x). Off here: overtake's
    Steps reach a trainer on the server's host through overtake's own segment
    (:mod:`.shared_memory`), and Zenoh's leaves its segments in /dev/shm when a process ends
    (a 1.3 MB one for each process, and each 16 MB pool a peer mapped stays with that peer
    for its life: eclipse-zenoh/zenoh#2787), tmpfs memory no one gives back."""
    extra_json5: tuple[tuple[str, str], ...] = field(default=())
    """More Zenoh settings as (key, JSON5 value) pairs."""

    def zenoh_config(self) -> zenoh.Config:
        check_endpoints("--listen", self.listen)
        check_endpoints("--connect", self.connect)
        self.security.check(self.listen, self.connect)
        if self.mode == "client" and self.security.credentials_file is not None:
            # The commands share one set of security options; on a client this one would be
            # silently ignored, and its user would believe the link guarded.
            raise ConnectError(
                f"--credentials-file {self.security.credentials_file} lists the "
                "users a listening server or router admits; this command only "
                "connects. To authenticate, give --user NAME with "
                f"--password-file PATH (or ${PASSWORD_ENV})"
            )
        conf = zenoh.Config()
        conf.insert_json5("mode", json.dumps(self.mode))
        conf.insert_json5("scouting/multicast/enabled", "false")
        conf.insert_json5("scouting/gossip/enabled", "false")
        conf.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        conf.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
        if self.connect:
            timeout_ms = max(int(self.connect_timeout_s * 1000), 0)
            conf.insert_json5("connect/timeout_ms", str(timeout_ms))
            conf.insert_json5(
                "connect/retry",
                "{ period_init_ms: 100, period_max_ms: 1000, period_increase_factor: 2 }",
            )
            if self.mode != "client":
                # Peers and routers must not fail to start when the other side is not up yet.
                conf.insert_json5("connect/exit_on_failure", "false")
        lease_ms = max(int(self.lease_s * 1000), 200)
        conf.insert_json5("transport/link/tx/lease", str(lease_ms))
        conf.insert_json5("transport/link/tx/keep_alive", "4")
        conf.insert_json5("transport/shared_memory/enabled", json.dumps(self.zenoh_shared_memory))
        for key, value in self.security.zenoh_settings() + list(self.extra_json5):
            conf.insert_json5(key, value)
        return conf

    def describe(self) -> str:
        parts: list[str] = [self.mode]
        if self.listen:
            parts.append("listening on " + ", ".join(self.listen))
        if self.connect:
            parts.append("connecting to " + ", ".join(self.connect))
        return " ".join(parts)


def open_session(config: TransportConfig) -> zenoh.Session:
    """A Zenoh session; raises ``zenoh.ZError`` as Zenoh does (callers add the likely causes),
    or :class:`ConnectError` for credentials or certificates that cannot be used."""
    return zenoh.open(config.zenoh_config())


# --- why a connection failed ----------------------------------------------------------------
# Zenoh reports every failure to connect as "Unable to connect to any of [...]", whether nobody
# listens, the certificate is not trusted or the password is wrong. Trying the link by hand
# (TCP, then the TLS handshake with the same certificates) tells those apart.

PROBE_TIMEOUT_S = 2.0


def on_zenoh_thread(callback: Callable[[T], object]) -> zenoh.handlers.Callback[T]:
    """``callback`` as a subscriber's handler that Zenoh calls on its own receiving thread.

    zenoh-python's default runs a plain callable on a Python thread of its own, one a
    subscriber, which is not a daemon and lives until the subscriber is undeclared: a process
    that never closes its session (a script that drops its environment without ``close()``)
    then waits for those threads at exit, forever. Called on Zenoh's thread the callback must
    be short (ours only put on a queue or set flags); it also saves a thread hand-over a
    message. (``indirect`` is marked unstable in zenoh-python 1.x.)"""
    return zenoh.handlers.Callback(callback, indirect=False)


def _tls_context(security: SecurityConfig) -> ssl.SSLContext:
    context = ssl.create_default_context(
        cafile=str(security.tls_root_ca) if security.tls_root_ca is not None else None
    )
    context.check_hostname = security.tls_verify_name
    if security.tls_mtls and security.tls_certificate is not None:
        context.load_cert_chain(str(security.tls_certificate), str(security.tls_private_key))
    return context


def _speaks_tls(host: str, port: int) -> bool:
    """Whether the listener answers a TLS handshake (certificates not checked)."""
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    context.check_hostname = False
    context.verify_mode = ssl.CERT_NONE
    try:
        with (
            socket.create_connection((host, port), timeout=1.0) as sock,
            context.wrap_socket(sock, server_hostname=host),
        ):
            return True
    except (OSError, ssl.SSLError):
        return False


def _tls_cause(host: str, port: int, security: SecurityConfig) -> str | None:
    where = f"{host}:{port}"
    try:
        context = _tls_context(security)
    except (OSError, ssl.SSLError) as error:
        return f"this side's TLS files cannot be used ({error})"
    try:
        with (
            socket.create_connection((host, port), timeout=PROBE_TIMEOUT_S) as sock,
            context.wrap_socket(sock, server_hostname=host) as tls,
        ):
            # With TLS 1.3 a listener that wants a client certificate says so only after
            # the handshake: wait briefly for its alert (a Zenoh router sends nothing).
            tls.settimeout(0.5)
            try:
                tls.recv(1)
            except ssl.SSLError as error:
                if "CERTIFICATE_REQUIRED" in str(error).upper() or not security.tls_mtls:
                    return (
                        f"{where} requires a client certificate (mutual TLS): give "
                        "--tls-mtls with --tls-certificate and --tls-private-key signed "
                        "by a CA it trusts"
                    )
                if "EXPIRED" in str(error).upper():
                    return (
                        f"{where} refused this side's certificate: it has expired "
                        f"({error.reason or error}); make a new one for "
                        f"--tls-certificate {security.tls_certificate} with the same CA "
                        "(scripts/make-certs.sh)"
                    )
                return (
                    f"{where} refused this side's certificate "
                    f"({error.reason or error}): it is not signed by a CA it trusts"
                )
            except (TimeoutError, OSError):
                pass
    except ssl.SSLCertVerificationError as error:
        reason = error.verify_message or str(error)
        if "expired" in reason.lower() or "not yet valid" in reason.lower():
            return (
                f"the TLS certificate of {where} {reason.lower().removeprefix('certificate ')}"
                ": the router needs a new one from its CA (scripts/make-certs.sh), or this "
                "machine's clock is wrong"
            )
        if "mismatch" in reason.lower():
            return (
                f"the TLS certificate of {where} does not name {host!r} ({reason}): connect "
                "with a name or address its certificate lists (its subjectAltName)"
            )
        if security.tls_root_ca is None:
            return (
                f"the TLS certificate of {where} is not trusted ({reason}): give the CA "
                "certificate that signed it with --tls-root-ca"
            )
        return (
            f"the TLS certificate of {where} is not trusted ({reason}): it is not signed "
            f"by the CA in --tls-root-ca {security.tls_root_ca}"
        )
    except ssl.SSLError as error:
        return (
            f"{where} does not complete a TLS handshake ({error.reason or error}): is it a "
            "tcp/ listener rather than tls/?"
        )
    except OSError:
        return None  # reachable a moment ago; the caller reports what it found
    return None


def connect_failure_cause(config: TransportConfig) -> str | None:
    """The likely cause of a failure to connect to ``config.connect``, found by trying each
    endpoint's link by hand; None when no endpoint could be tried (e.g. udp or quic)."""
    causes = []
    for endpoint in config.connect:
        scheme, address = protocol_of(endpoint), host_port(endpoint)
        if scheme not in ("tcp", "tls") or address is None:
            continue
        host, port = address
        where = f"{host}:{port}"
        try:
            socket.create_connection((host, port), timeout=PROBE_TIMEOUT_S).close()
        except OSError as error:
            causes.append(
                f"nothing accepts connections at {where} "
                f"({error.strerror or error}). Likely causes: no router or server "
                "runs there; a wrong host or port; it listens on loopback only (start "
                "it with --listen tcp/0.0.0.0:7447 to let other hosts in); a firewall"
            )
            continue
        if scheme == "tls":
            cause = _tls_cause(host, port, config.security)
            if cause is not None:
                causes.append(cause)
                continue
        elif _speaks_tls(host, port):
            causes.append(f"{where} is a TLS listener: connect to tls/{where} (with --tls-root-ca)")
            continue
        credentials = config.security.user_name()
        if credentials:
            causes.append(
                f"{where} accepted the link but refused the Zenoh session: most "
                f"likely a wrong password for user {credentials!r}, or a user its "
                "credentials file does not list"
            )
        else:
            causes.append(
                f"{where} accepted the link but refused the Zenoh session: most "
                "likely it requires usrpwd credentials (--user, with --password-file "
                f"or ${PASSWORD_ENV})"
            )
    return "; ".join(causes) if causes else None


# --- listeners anyone may use ----------------------------------------------------------------

# Schemes whose endpoints are network addresses (unixsock-stream, unixpipe, serial are local).
_NETWORK_SCHEMES = ("tcp", "udp", "tls", "quic", "ws")
# Schemes whose links carry TLS, where mutual TLS decides who gets in.
_TLS_SCHEMES = ("tls", "quic")


def is_loopback_endpoint(endpoint: str) -> bool:
    """Whether ``endpoint`` listens on loopback only (127.x, ::1, localhost)."""
    address = host_port(endpoint)
    if address is None:
        return False
    host = address[0].split("%")[0].lower()
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False  # a host name: other hosts may reach it


def unguarded_listeners(listen: tuple[str, ...], *, usrpwd: bool, mtls: bool) -> tuple[str, ...]:
    """The network endpoints in ``listen`` that anyone who reaches them may use: not loopback,
    and guarded neither by usrpwd (a credentials file, checked on every link) nor, for tls/ and
    quic/ endpoints, by mutual TLS."""
    if usrpwd:
        return ()
    return tuple(
        endpoint
        for endpoint in listen
        if protocol_of(endpoint) in _NETWORK_SCHEMES
        and not is_loopback_endpoint(endpoint)
        and not (mtls and protocol_of(endpoint) in _TLS_SCHEMES)
    )


def warn_if_unguarded(
    config: TransportConfig, log: logging.Logger, *, usrpwd: bool = False, mtls: bool = False
) -> tuple[str, ...]:
    """Log one warning naming the listeners anyone may use (see
    :func:`unguarded_listeners`); returns them. usrpwd and mutual TLS count when
    ``config.security`` sets them or the caller says another source does (a router's file)."""
    security = config.security
    unguarded = unguarded_listeners(
        config.listen,
        usrpwd=usrpwd or security.credentials_file is not None,
        mtls=mtls or security.tls_mtls,
    )
    if unguarded:
        log.warning(
            "listening on %s with neither usrpwd nor mutual TLS: anyone who reaches that "
            "address can join this Zenoh network, drive the simulator and read "
            "everything on it. Listen on loopback only (tcp/127.0.0.1:PORT), or admit "
            "only known users (--credentials-file) or certificates (tls/ endpoints with "
            "--tls-mtls); docs/remote-hosts.md",
            ", ".join(unguarded),
        )
    return unguarded


def warn_if_unconnected(
    session: zenoh.Session, config: TransportConfig, log: logging.Logger, after_s: float = 10.0
) -> threading.Thread | None:
    """A router or peer keeps retrying its ``connect`` endpoints in the background rather than
    failing (it may start before them): if none is connected after ``after_s``, say so once,
    with the likely cause, instead of waiting in silence."""
    if not config.connect:
        return None

    def check() -> None:
        try:
            if list(session.info.routers_zid()) or list(session.info.peers_zid()):
                return
        except Exception:  # the session closed in the meantime
            return
        cause = connect_failure_cause(config)
        log.warning(
            "not connected to %s after %.0f s (still trying)%s",
            ", ".join(config.connect),
            after_s,
            f": {cause}" if cause else "",
        )

    timer = threading.Timer(after_s, check)
    timer.daemon = True
    timer.start()
    return timer
