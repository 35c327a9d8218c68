"""What the server sends: each member's rounds through its channel
(:mod:`overtake.server.channels`: Zenoh frames, or a shared-memory segment with a doorbell for
a trainer on this host that holds its group alone), and each watched arena's world frames for
spectators, dropped under congestion so that watching never holds the simulation back.

The outbox owns the channels: a Zenoh one per trainer holding arenas here, a shared-memory one
per group a trainer holds alone and asked for, closed when the trainer leaves the group, goes
away or the server closes."""

from __future__ import annotations

import logging
from collections.abc import Callable

import zenoh

from overtake.ipc.doorbell import AVAILABLE as DOORBELL_AVAILABLE
from overtake.protocol import codec, keys
from overtake.protocol.messages import ErrorReply, Message, ShmOffer, Steps

from .channels import StepsChannel
from .channels.shm_channel import ShmChannel
from .channels.zenoh_channel import ZenohChannel, send_once
from .groups import Group
from .world import group_world_frame

log = logging.getLogger(__name__)


class Outbox:
    """The server's channels to its trainers, and its world publishers, on its Zenoh
    ``session``. ``on_ring(trainer, group)``: a trainer rang its segment's Actions bell (called
    on the channel's thread; it should only enqueue)."""

    def __init__(
        self,
        session: zenoh.Session,
        server: str,
        world_rate_hz: float,
        on_ring: Callable[[str, int], None] = lambda trainer, group: None,
    ) -> None:
        self.session, self.server = session, server
        self.world_rate_hz = world_rate_hz
        self._on_ring = on_ring
        self._zenoh: dict[str, ZenohChannel] = {}
        self._shm: dict[tuple[str, int], ShmChannel] = {}
        self._world_pubs: dict[int, zenoh.Publisher] = {}
        self._last_world: dict[int, float] = {}

    # --- channels ------------------------------------------------------------------------------

    def open_for(self, trainer: str) -> None:
        """Keep a Zenoh channel for ``trainer`` (it holds arenas here)."""
        if trainer not in self._zenoh:
            self._zenoh[trainer] = ZenohChannel(self.session, self.server, trainer)

    def offer_segment(self, group: Group, trainer: str) -> ShmOffer | None:
        """A shared-memory channel for ``trainer``'s rounds of ``group`` (which it holds
        alone), sized for its current Steps; None where one cannot be made (said in the log)."""
        if not DOORBELL_AVAILABLE:
            log.info("no futex doorbell on this machine: %s's Steps go over Zenoh", trainer)
            return None
        self.open_for(trainer)
        self.forget_member(group.group_id, trainer)
        try:
            channel = ShmChannel.create(
                group.current_steps(trainer),
                trainer,
                group.members[trainer].ticket,
                self._zenoh[trainer],
                self._on_ring,
            )
        except OSError as error:
            log.warning("no shared memory for %s (Steps go over Zenoh): %s", trainer, error)
            return None
        self._shm[(trainer, group.group_id)] = channel
        return channel.offer()

    def segment_channel(self, trainer: str, group: int) -> ShmChannel | None:
        """``trainer``'s shared-memory channel of ``group``, if it has one."""
        return self._shm.get((trainer, group))

    def rung(self) -> list[ShmChannel]:
        """The shared-memory channels whose trainer rang since the loop took its Actions."""
        return [channel for channel in self._shm.values() if channel.rung()]

    @property
    def has_segments(self) -> bool:
        return bool(self._shm)

    def actions_over_zenoh(self, trainer: str, group: int) -> None:
        """``trainer``'s Actions for ``group`` came over Zenoh: it does not read the segment
        (it chose Zenoh, could not map it, or speaks 1.6), so the segment goes."""
        self.forget_member(group, trainer)

    def send_steps(self, group: Group, trainer: str, steps: Message) -> None:
        """``trainer``'s Steps of a round of ``group`` (or what replaced them): through its
        segment where it has one and holds the group alone; a shared group steps on a
        deadline, which could overwrite a round a member is still reading, so there the round
        goes over Zenoh, rung in the segment all the same (its trainer sleeps on the bell)."""
        shm = self._shm.get((trainer, group.group_id))
        if shm is not None:
            if isinstance(steps, Steps) and len(group.members) == 1:
                shm.send_steps(steps)
            else:
                shm.send(steps)
            return
        channel = self._zenoh.get(trainer)
        if channel is None:
            send_once(self.session, self.server, trainer, steps)
        else:
            channel.send(steps)

    def send(self, trainer: str, message: Message) -> None:
        """What is not a round (an error reply): over Zenoh, and where it is about a group
        whose rounds go through a segment, counted and rung there too."""
        group = message.group if isinstance(message, ErrorReply) else None
        channel: StepsChannel | None = None
        if group is not None:
            channel = self._shm.get((trainer, group))
        if channel is None:
            channel = self._zenoh.get(trainer)
        if channel is not None:
            channel.send(message)
        else:  # a trainer with no arenas here: no channel kept for it
            send_once(self.session, self.server, trainer, message)

    def forget_member(self, group: int, trainer: str) -> None:
        """Close ``trainer``'s segment of ``group`` (it left the group)."""
        channel = self._shm.pop((trainer, group), None)
        if channel is not None:
            channel.close()

    def close(self) -> None:
        """Close every channel (the server stops)."""
        for trainer, group in list(self._shm):
            self.forget_member(group, trainer)
        for channel in self._zenoh.values():
            channel.close()
        self._zenoh.clear()

    def forget_trainer(self, trainer: str) -> None:
        for held_by, group in list(self._shm):
            if held_by == trainer:
                self.forget_member(group, trainer)
        channel = self._zenoh.pop(trainer, None)
        if channel is not None:
            channel.close()

    # --- spectators -----------------------------------------------------------------------------

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
            pub.put(codec.encode(group_world_frame(group, index, observations)))

    def forget_group(self, group: Group) -> None:
        """The group's arenas are freed: their world publishers and segments go."""
        for trainer, group_id in list(self._shm):
            if group_id == group.group_id:
                self.forget_member(group_id, trainer)
        for arena in group.arena_ids:
            pub = self._world_pubs.pop(arena, None)
            if pub is not None:
                pub.undeclare()
        self._last_world.pop(group.group_id, None)
