"""How a round reaches a trainer and its answer comes back: one channel per way, each behind
the same small interface (:class:`StepsChannel`), so that a transport is added in one module.

- :mod:`.zenoh_channel`: Steps frames on the trainer's key, Actions on the server's (any host);
- :mod:`.shm_channel`: Steps and Actions through a shared-memory segment with a futex doorbell
  (a trainer on this host that holds its group alone; protocol 1.7).

The outbox (:mod:`overtake.server.outbox`) picks a member's channel; the service loop hands it
each round's Steps and whatever else the member must hear (an error), and receives the
member's Actions from the inbox, whichever channel they came through.
"""

from __future__ import annotations

from typing import Protocol

from overtake.protocol.messages import Message, Steps


class StepsChannel(Protocol):
    """One member's way to its trainer: what the server does with a round."""

    def send_steps(self, steps: Steps) -> None:
        """Deliver a round's Steps."""

    def send(self, message: Message) -> None:
        """Deliver what is not a round (an error reply)."""

    def close(self) -> None:
        """Stop: the member left, its trainer went away, or the server stops (idempotent)."""
