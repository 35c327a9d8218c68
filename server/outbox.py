"""What the server sends: each trainer's Steps (and error replies) on its own key, with blocking
congestion control so that no step is silently lost, and each watched arena's world frames
for spectators, dropped under congestion so that watching never holds the simulation back."""

from __future__ import annotations

import zenoh

from overtake.protocol import codec, keys
from overtake.protocol.messages import Message

from .groups import Group


class Outbox:
    """The server's publishers on its Zenoh ``session``."""

    def __init__(self, session: zenoh.Session, server: str, world_rate_hz: float) -> None:
        self.session, self.server = session, server
        self.world_rate_hz = world_rate_hz
        self._step_pubs: dict[str, zenoh.Publisher] = {}
        self._world_pubs: dict[int, zenoh.Publisher] = {}
        self._last_world: dict[int, float] = {}

    def open_for(self, trainer: str) -> None:
        """Keep a publisher for ``trainer``'s Steps (it holds arenas here)."""
        if trainer not in self._step_pubs:
            self._step_pubs[trainer] = self.session.declare_publisher(
                keys.trainer_steps(trainer, self.server),
                congestion_control=zenoh.CongestionControl.BLOCK,
                priority=zenoh.Priority.DATA_HIGH,
            )

    def send(self, trainer: str, message: Message) -> None:
        pub = self._step_pubs.get(trainer)
        if pub is not None:
            pub.put(codec.encode(message))
        else:  # a trainer with no arenas here (an error reply): no publisher kept for it
            self.session.put(
                keys.trainer_steps(trainer, self.server),
                codec.encode(message),
                congestion_control=zenoh.CongestionControl.BLOCK,
            )

    def forget_trainer(self, trainer: str) -> None:
        pub = self._step_pubs.pop(trainer, None)
        if pub is not None:
            pub.undeclare()

    def publish_world(self, group: Group, now: float) -> None:
        """``group``'s arenas to whoever watches them, at most ``world_rate_hz`` frames a
        second each; an arena nobody watches costs no encoding."""
        rate = self.world_rate_hz
        if rate <= 0 or now - self._last_world.get(group.group_id, 0.0) < 1.0 / rate:
            return
        self._last_world[group.group_id] = now
        observations = None
        for index, arena in enumerate(group.arena_ids):
            pub = self._world_pubs.get(arena)
            if pub is None:
                pub = self._world_pubs[arena] = self.session.declare_publisher(
                    keys.world(self.server, arena),
                    congestion_control=zenoh.CongestionControl.DROP,
                    priority=zenoh.Priority.DATA_LOW,
                )
            # zenoh 1.10's stubs say bool; it is a MatchingStatus.
            if not pub.matching_status.matching:  # type: ignore[attr-defined]
                continue
            if observations is None:
                observations = group.latest_observations()
            pub.put(codec.encode(group.world_frame(index, observations)))

    def forget_group(self, group: Group) -> None:
        """The group's arenas are freed: their world publishers go."""
        for arena in group.arena_ids:
            pub = self._world_pubs.pop(arena, None)
            if pub is not None:
                pub.undeclare()
        self._last_world.pop(group.group_id, None)
