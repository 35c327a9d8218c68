"""How a trainer's rounds travel, behind one small interface (:class:`StepsChannel`), so that a
transport is one module on this side (and one on the server's, :mod:`overtake.server.channels`):

- :mod:`.zenoh_channel`: Actions on the server's key, Steps on this trainer's (any host);
- :mod:`.shm_channel`: both through the shared-memory segment the server offered, with a futex
  doorbell each way (a trainer on the server's host; protocol 1.7).

The connection (:mod:`.connection`) holds one channel per group it steps and waits in one loop:
it takes a round from the channel, or from its Zenoh inbox, where whatever is not a round
(an error) arrives for every transport.

The negotiation names transports (protocol 1.10): the open request lists those this side can
take (:func:`requested_transports`: :data:`ATTACH`'s, by the trainer's setting), the server
offers at most one (a :class:`~overtake.protocol.channel_offers.ChannelOffer` tagged with its
name) and :func:`open_channel` takes it with that transport's :data:`ATTACH` entry.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal, Protocol, runtime_checkable

from overtake.protocol.channel_offers import ZENOH, ChannelOffer
from overtake.protocol.messages import Actions, Opened, ShmOffer, Steps

Transport = Literal["auto", "shm", "zenoh"]
"""How a trainer's rounds travel: ``shm`` through shared memory (the server must be on this
host, sharing its ``/dev/shm``), ``zenoh`` always over Zenoh, ``auto`` through shared memory
wherever the server's segment can be attached, over Zenoh otherwise. With the doorbell a round
through the segment sends no Zenoh message at all, and it gains at every size measured
(bench/RESULTS.md, issue 47: 1, 8 and 64 arenas of min2018), so ``auto`` no longer looks at the
size as protocol 1.6's notice path had to (256 KiB)."""


@runtime_checkable
class StepsChannel(Protocol):
    """One group's way to and from its server, on the trainer's side."""

    name: str
    """the transport's name (``zenoh``, ``shm``), which ``Connection.rounds_through`` counts by"""
    rounds: int
    """rounds whose Steps this channel delivered itself (not through the Zenoh inbox)"""

    def send_actions(self, actions: Actions) -> None:
        """Deliver a round's Actions to the server."""

    def take(self, round_: int) -> Steps | None:
        """Round ``round_``'s Steps if this channel holds them, without waiting (once)."""

    def wait(self, timeout_s: float, spin_s: float) -> bool:
        """Wait until this channel may hold something, up to ``timeout_s``; False at once where
        what comes next comes through the Zenoh inbox (the caller waits there instead)."""

    def heard_over_zenoh(self) -> None:
        """A message for this group arrived through the Zenoh inbox (a channel that counts
        what its server sent that way stops waiting for it)."""

    def wake(self) -> None:
        """End a :meth:`wait` (the server's token went: the waiter looks at it)."""

    def close(self, unlink: bool) -> None:
        """Stop (idempotent); ``unlink``: the server is gone, remove what it would have."""


Attach = Callable[[str, int, ChannelOffer | None, bool], "StepsChannel | None"]
"""Takes a transport's channel: ``(server, group, offer, required)``, the offer None where the
server made none; returns the channel, or None where this side cannot take it (the rounds
then go over Zenoh; said in the log), and with ``required`` raises
:class:`~overtake.protocol.errors.ConnectError` saying why instead."""


def _attach_shm(
    server: str, group: int, offer: ChannelOffer | None, required: bool
) -> StepsChannel | None:
    from overtake.client.wire.shm_channel import attach  # the segment's ctypes load here

    return attach(server, group, offer if isinstance(offer, ShmOffer) else None, required)


ATTACH: dict[str, Attach] = {"shm": _attach_shm}
"""The channels this side can take besides Zenoh, by transport name, preferred first."""


def requested_transports(transport: Transport) -> tuple[str, ...]:
    """What an open request lists for ``transport``: nothing for ``zenoh``, every channel
    this side can take for ``auto`` (in :data:`ATTACH`'s order), else that one."""
    if transport == ZENOH:
        return ()
    return tuple(ATTACH) if transport == "auto" else (transport,)


def offered(opened: Opened) -> ChannelOffer | None:
    """The channel a server's reply offers (a 1.9 server fills only the segment's field)."""
    return opened.offer if opened.offer is not None else opened.shm


def open_channel(
    server: str,
    group: int,
    offer: ChannelOffer | None,
    transport: Transport,
    over_zenoh: Callable[[], StepsChannel],
) -> StepsChannel:
    """The channel ``group``'s rounds take: the server's offer where ``transport`` allows it
    and this side can take it, else ``over_zenoh()``. With a named ``transport`` (not
    ``auto``) an offer missing or out of reach is an error
    (:class:`~overtake.protocol.errors.ConnectError`) that says why."""
    channel = None
    wanted = requested_transports(transport)
    if offer is not None and offer.TRANSPORT in wanted:
        channel = ATTACH[offer.TRANSPORT](server, group, offer, transport == offer.TRANSPORT)
    elif transport not in ("auto", ZENOH):
        channel = ATTACH[transport](server, group, None, True)  # says why none came
    return channel if channel is not None else over_zenoh()
