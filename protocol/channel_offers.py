"""Which way a group's rounds travel (protocol 1.10): Zenoh, which every peer has, or a channel
the server offers a trainer that asked for it.

An :class:`~overtake.protocol.messages.OpenRequest` names the transports the trainer can read
(``transports``, in its order of preference) and the server answers with at most one
:class:`ChannelOffer` (``Opened.offer``), tagged on the wire with its transport's name. A
transport is one offer type here (a subclass of :class:`ChannelOffer` with its ``TRANSPORT``
name; defining it registers it with the codec) and one module on each side
(:mod:`overtake.server.channels`, :mod:`overtake.client.wire.steps_channel`).

Before 1.10 the negotiation named shared memory's fields (``OpenRequest.shm``,
``Opened.shm``); both sides still fill them, so older peers negotiate as they did.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from .errors import DecodeError
from .records import Part, check_name, check_names

ZENOH = "zenoh"
"""The transport every peer has: Steps frames on the trainer's key, Actions on the server's."""
MAX_TRANSPORTS = 8  # names an open request may list

_OFFER_TYPES: dict[str, type[ChannelOffer]] = {}


@dataclass(frozen=True, eq=False)
class ChannelOffer(Part):
    """A channel the server offers for a member's rounds, instead of Zenoh frames; a subclass
    per transport, named by ``TRANSPORT`` (its tag on the wire)."""

    TRANSPORT: ClassVar[str] = ""

    def __init_subclass__(cls, **kwargs: object) -> None:
        super().__init_subclass__(**kwargs)
        check_name("transport", cls.TRANSPORT)
        if cls.TRANSPORT == ZENOH:
            raise TypeError(f"{cls.__name__}: Zenoh is every peer's transport, not an offer")
        taken = _OFFER_TYPES.get(cls.TRANSPORT)
        # The same class defined again (a module reloaded) takes its name back.
        if taken is not None and taken.__qualname__ != cls.__qualname__:
            raise TypeError(
                f"{cls.__name__}: transport {cls.TRANSPORT!r} is {taken.__qualname__}'s"
            )
        _OFFER_TYPES[cls.TRANSPORT] = cls


def offer_type(transport: str) -> type[ChannelOffer]:
    """The offer type of ``transport`` (the codec decodes a tagged offer by it)."""
    cls = _OFFER_TYPES.get(transport)
    if cls is None:
        raise DecodeError(
            f"expected a channel offer of {', '.join(sorted(_OFFER_TYPES)) or 'no transport'}, "
            f"got {transport!r}"
        )
    return cls


def offered_transports() -> tuple[str, ...]:
    """Every transport a server may offer (besides Zenoh), in the order their types were
    defined."""
    return tuple(_OFFER_TYPES)


def check_transports(names: tuple[str, ...]) -> None:
    """An open request's list: valid, distinct names, at most :data:`MAX_TRANSPORTS`. Names
    this side does not know are allowed: a newer trainer may list more than a server offers."""
    check_names("transport", names, MAX_TRANSPORTS)
