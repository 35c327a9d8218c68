"""Zenoh endpoints as written: ``PROTOCOL/ADDRESS[?config][#metadata]``, their protocol, host
and port, and the check that refuses a malformed one with its corrected form."""

from __future__ import annotations

from overtake.protocol.errors import ConnectError


def protocol_of(endpoint: str) -> str:
    """The link protocol an endpoint names (``tcp`` of ``tcp/127.0.0.1:7447``), lower case."""
    return endpoint.partition("/")[0].lower()


# Zenoh 1.x's link protocols, the part of an endpoint before its first "/".
ENDPOINT_SCHEMES = (
    "tcp", "udp", "tls", "quic", "ws", "unixsock-stream", "unixpipe", "serial", "vsock",
)  # fmt: skip


def check_endpoints(flag: str, endpoints: tuple[str, ...]) -> None:
    """Refuse, in one line with the corrected form, an endpoint that is not
    ``PROTOCOL/ADDRESS`` (``127.0.0.1:7447`` for ``tcp/127.0.0.1:7447``, ``tcp://...``):
    Zenoh would only say that no session opened."""
    for endpoint in endpoints:
        scheme, slash, address = endpoint.partition("/")
        if slash and scheme.lower() in ENDPOINT_SCHEMES and address and not address.startswith("/"):
            continue
        # The address as written, with any "scheme://" or "scheme/" in front taken away.
        given, sep, rest = endpoint.partition("://")
        if not sep:
            given, rest = "", address if slash else endpoint
        proto = given.lower() if given.lower() in ENDPOINT_SCHEMES else "tcp"
        raise ConnectError(
            f"{flag} {endpoint}: an endpoint is PROTOCOL/ADDRESS, one of "
            f"{', '.join(ENDPOINT_SCHEMES[:5])}, ...; did you mean {flag} {proto}/{rest}?"
        )


def host_port(endpoint: str) -> tuple[str, int] | None:
    """Host and port of ``proto/host:port[?config][#metadata]``; None if it has none."""
    address = endpoint.partition("/")[2].split("?")[0].split("#")[0]
    host, sep, port = address.rpartition(":")
    if not sep or not port.isdigit():
        return None
    return host.strip("[]"), int(port)
