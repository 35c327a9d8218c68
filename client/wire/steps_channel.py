"""How a trainer's rounds travel, behind one small interface (:class:`StepsChannel`), so that a
transport is one module on this side (and one on the server's, :mod:`overtake.server.channels`):

- :mod:`.zenoh_channel`: Actions on the server's key, Steps on this trainer's (any host);
- :mod:`.shm_channel`: both through the shared-memory segment the server offered, with a futex
  doorbell each way (a trainer on the server's host; protocol 1.7).

The connection (:mod:`.connection`) holds one channel per group it steps and waits in one loop:
it takes a round from the channel, or from its Zenoh inbox, where whatever is not a round
(an error) arrives for every transport; :func:`open_channel` picks the channel from the
server's reply and the trainer's setting.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal, Protocol, runtime_checkable

from overtake.client.wire.shm_channel import attach
from overtake.protocol.messages import Actions, ShmOffer, Steps

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


def open_channel(
    server: str,
    group: int,
    offer: ShmOffer | None,
    transport: Transport,
    over_zenoh: Callable[[], StepsChannel],
) -> StepsChannel:
    """The channel ``group``'s rounds take: the server's offered segment where ``transport``
    allows it and this trainer can attach it, else ``over_zenoh()``. With ``transport="shm"``
    a missing or unreachable segment is an error (:class:`~overtake.protocol.errors.ConnectError`)
    that says why."""
    channel = None
    if transport != "zenoh":
        channel = attach(server, group, offer, required=transport == "shm")
    return channel if channel is not None else over_zenoh()
