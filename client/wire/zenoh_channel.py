"""Rounds over Zenoh, on the trainer's side: a round's Actions put on the server's actions key,
its Steps arriving on this trainer's own key, in the connection's inbox with every other group's
(one subscriber per trainer: :mod:`.connection` files them). Any host can use it."""

from __future__ import annotations

import zenoh

from overtake.protocol import codec
from overtake.protocol.messages import Actions, Steps


class ZenohChannel:
    """A group's rounds over Zenoh; the publisher is the connection's, shared by every group
    this trainer steps on the same server."""

    name = "zenoh"

    def __init__(self, publisher: zenoh.Publisher) -> None:
        self._publisher = publisher
        self.rounds = 0  # its Steps come through the Zenoh inbox, not through this channel

    def send_actions(self, actions: Actions) -> None:
        self._publisher.put(codec.encode(actions))

    def take(self, round_: int) -> Steps | None:
        return None  # the connection takes this group's Steps from its Zenoh inbox

    def wait(self, timeout_s: float, spin_s: float) -> bool:
        return False  # what comes, comes through the Zenoh inbox

    def heard_over_zenoh(self) -> None:
        pass

    def wake(self) -> None:
        pass  # a waiter on the Zenoh inbox wakes within its own poll

    def close(self, unlink: bool) -> None:
        pass  # the publisher stays with the connection, for the server's other groups
