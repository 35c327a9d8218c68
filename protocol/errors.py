"""One error hierarchy for everything that can go wrong on the wire.

Every error says what was expected and what came. :class:`ProtocolError` is the base; the
server turns any of them into an :class:`~overtake.protocol.messages.ErrorReply` carrying the
error's ``code``, and the client raises the matching class again from that reply
(:func:`error_from_code`), so a trainer sees the server's own words.
"""

from __future__ import annotations


class ProtocolError(Exception):
    """Base of every overtake wire error. ``code`` travels in error replies."""

    code = "protocol_error"


class DecodeError(ProtocolError):
    """Bytes that are not a well-formed overtake frame, or a frame whose fields are wrong."""

    code = "bad_message"


class VersionMismatch(ProtocolError):
    """The peer speaks a protocol whose major version differs from ours."""

    code = "version_mismatch"


class UnknownPreset(ProtocolError):
    code = "unknown_preset"


class BadConfig(ProtocolError, ValueError):
    """An override names no field, or gives a value of the wrong type or range: the one error
    of a configuration mistake, wherever it is found (the simulator's configuration raises it
    as ``overtake.server.sim.ConfigError``, the same class), so a ``ValueError`` too."""

    code = "bad_config"


class ServerFull(ProtocolError):
    code = "server_full"


class ServerBusy(ProtocolError):
    """Too many requests wait at the server (a flood): this one was not queued; ask again."""

    code = "server_busy"


class UnknownArena(ProtocolError):
    """The arena (or group) does not exist on this server: never opened, or closed since."""

    code = "unknown_arena"


class NotOwner(ProtocolError):
    """A trainer sent actions or requests for agents it did not open or join."""

    code = "not_owner"


class WrongTicket(NotOwner):
    """A request or actions in a trainer's name without the ticket its open or join got."""

    code = "wrong_ticket"


class BadAction(ProtocolError):
    code = "bad_action"


class StaleActions(ProtocolError):
    """Actions for a round the group already played without them (at the deadline): the
    server drops them quietly; the trainer finds that round's Steps marked late."""

    code = "stale_actions"


class ConnectError(ProtocolError):
    """No overtake server could be reached (or none answered) within the configured time."""

    code = "connect_error"


class ServerLost(ProtocolError):
    """The server went away while we were waiting on it."""

    code = "server_lost"


class StepTimeout(ProtocolError):
    """A reply or an observation did not come within the configured timeout."""

    code = "timeout"


class Interrupted(ProtocolError):
    """This process was asked to stop while it waited on a server (a round that did not
    come, a lost server not back yet); raised on this side only, never sent."""

    code = "interrupted"


ERRORS_BY_CODE: dict[str, type[ProtocolError]] = {
    cls.code: cls
    for cls in (
        ProtocolError,
        DecodeError,
        VersionMismatch,
        UnknownPreset,
        BadConfig,
        ServerFull,
        ServerBusy,
        UnknownArena,
        NotOwner,
        WrongTicket,
        BadAction,
        StaleActions,
        ConnectError,
        ServerLost,
        StepTimeout,
        Interrupted,
    )
}


def error_from_code(code: str, message: str) -> ProtocolError:
    """The error class a code names (the base class for codes from a newer peer)."""
    return ERRORS_BY_CODE.get(code, ProtocolError)(message)
