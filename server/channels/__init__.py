"""How a round reaches a trainer and its answer comes back: one channel per way, each behind
the same small interface (:class:`StepsChannel`), so that a transport is added in one module.

- :mod:`.zenoh_channel`: Steps frames on the trainer's key, Actions on the server's (any host);
  every member has one;
- :mod:`.shm_channel`: Steps and Actions through a shared-memory segment with a futex doorbell
  (a trainer on this host that holds its group alone; protocol 1.7).

A channel other than Zenoh is offered (protocol 1.10): the trainer's open request lists the
transports it can read, and the outbox makes the first of them this server has
(:data:`OFFERED`, by transport name, each an :class:`OfferedChannel`); the reply carries the
channel's :class:`~overtake.protocol.channel_offers.ChannelOffer`. The outbox
(:mod:`overtake.server.service.outbox`) hands each channel a round's Steps and whatever else the
member must hear (an error), and the service loop takes the Actions a trainer put in its offered
channel (:meth:`OfferedChannel.rung`, :meth:`OfferedChannel.actions`) as it takes Actions from
the inbox.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

from overtake.protocol.channel_offers import ChannelOffer
from overtake.protocol.messages import Actions, Message, Steps


class StepsChannel(Protocol):
    """One member's way to its trainer: what the server does with a round."""

    def send_steps(self, steps: Steps) -> None:
        """Deliver a round's Steps."""

    def send(self, message: Message) -> None:
        """Deliver what is not a round (an error reply)."""

    def close(self) -> None:
        """Stop: the member left, its trainer went away, or the server stops (idempotent)."""


class OfferedChannel(StepsChannel, Protocol):
    """A channel the server offers one member of one group instead of Zenoh frames.

    It carries rounds only while its trainer holds the group alone: a shared group steps on a
    deadline, so the outbox sends a shared group's rounds with :meth:`send` (the way what is
    not a round goes), which the channel must deliver all the same."""

    trainer: str
    group: int

    def offer(self) -> ChannelOffer:
        """What the trainer needs to take its rounds through this channel."""

    def rung(self) -> bool:
        """Whether the trainer put Actions here since the loop last took them."""

    def actions(self) -> Actions:
        """The trainer's Actions put here, checked as a decoded frame is
        (:class:`~overtake.protocol.errors.DecodeError` where malformed)."""

    def hear_rings(self, on: bool) -> None:
        """Whether the trainer's putting Actions here calls ``on_ring`` (on the channel's
        thread): on while the service loop sleeps on its inbox; off while it runs, when it
        looks at :meth:`rung` itself."""


@dataclass(frozen=True)
class ChannelTerms:
    """What a channel is made for: one member of one group, as it is when it opens."""

    trainer: str
    ticket: bytes  # the member's ticket (its Actions carry it)
    current: Steps  # the member's Steps as they are (they size the channel)
    fallback: StepsChannel  # the member's Zenoh channel: what the offered one cannot carry
    on_ring: Callable[[str, int], None]  # (trainer, group) put Actions: call on any thread


ChannelMaker = Callable[[ChannelTerms], OfferedChannel | None]
"""Makes a transport's channel for a member; None where this machine cannot (said in the log);
OSError where making it failed."""


def _make_shm(terms: ChannelTerms) -> OfferedChannel | None:
    from .shm_channel import make  # its ctypes and segment load only when offered

    return make(terms)


OFFERED: dict[str, ChannelMaker] = {"shm": _make_shm}
"""The channels this server can offer, by transport name (the trainer's list picks)."""
