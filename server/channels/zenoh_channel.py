"""Rounds over Zenoh: each trainer's Steps (and error replies) on its own key, with blocking
congestion control so that no round is silently lost. A trainer anywhere on the network can
use it; its Actions arrive on the server's actions key (:mod:`overtake.server.service.inbox`)."""

from __future__ import annotations

import zenoh

from overtake.protocol import codec, keys
from overtake.protocol.messages import Message, Steps


class ZenohChannel:
    """A trainer's Steps key on the server's ``session``, one publisher for all its groups."""

    def __init__(self, session: zenoh.Session, server: str, trainer: str) -> None:
        self._publisher: zenoh.Publisher | None = session.declare_publisher(
            keys.trainer_steps(trainer, server),
            congestion_control=zenoh.CongestionControl.BLOCK,
            priority=zenoh.Priority.DATA_HIGH,
        )

    def send_steps(self, steps: Steps) -> None:
        self.send(steps)

    def send(self, message: Message) -> None:
        if self._publisher is not None:
            self._publisher.put(codec.encode(message))

    def close(self) -> None:
        publisher, self._publisher = self._publisher, None
        if publisher is not None:
            publisher.undeclare()


def send_once(session: zenoh.Session, server: str, trainer: str, message: Message) -> None:
    """``message`` to a trainer that holds no arenas here (an error reply): no publisher kept."""
    session.put(
        keys.trainer_steps(trainer, server),
        codec.encode(message),
        congestion_control=zenoh.CongestionControl.BLOCK,
    )
