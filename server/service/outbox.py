"""What the server sends: each member's rounds through its channel
(:mod:`overtake.server.channels`: Zenoh frames, or a channel the trainer asked for and was
offered, such as a shared-memory segment with a doorbell for a trainer on this host that holds
its group alone), and each watched arena's world frames for spectators, dropped under
congestion so that watching never holds the simulation back.

The outbox owns the channels: a Zenoh one per trainer holding arenas here, an offered one per
group a trainer holds alone and asked for, closed when the trainer leaves the group, goes away
or the server closes."""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable, Iterator, Sequence

import zenoh

from overtake.protocol import codec, keys
from overtake.protocol.channel_offers import ChannelOffer
from overtake.protocol.messages import ErrorReply, Message, Steps

from ..channels import ChannelTerms, OfferedChannel, StepsChannel
from ..channels.zenoh_channel import ZenohChannel, send_once
from ..engine.world import group_world_frame
from .groups import Group
from .server_config import ServerConfig

log = logging.getLogger(__name__)


class Outbox:
    """The server's channels to its trainers, and its world publishers, on its Zenoh
    ``session``, as ``config`` says (its name, world rate and the channels it offers:
    :meth:`~overtake.server.service.server_config.ServerConfig.offered_channels`).
    ``on_ring(trainer, group)``: a trainer put its Actions in its offered channel (called on
    the channel's thread; it should only enqueue)."""

    def __init__(
        self,
        session: zenoh.Session,
        config: ServerConfig,
        on_ring: Callable[[str, int], None] = lambda trainer, group: None,
    ) -> None:
        self.session, self.server = session, config.name
        self.world_rate_hz = config.world_rate_hz
        self._on_ring = on_ring
        self._makers = config.offered_channels()
        self._zenoh: dict[str, ZenohChannel] = {}
        self._offered: dict[tuple[str, int], OfferedChannel] = {}
        self._world_pubs: dict[int, zenoh.Publisher] = {}
        self._last_world: dict[int, float] = {}

    # --- channels ------------------------------------------------------------------------------

    def open_for(self, trainer: str) -> None:
        """Keep a Zenoh channel for ``trainer`` (it holds arenas here)."""
        if trainer not in self._zenoh:
            self._zenoh[trainer] = ZenohChannel(self.session, self.server, trainer)

    def offer_channel(
        self, group: Group, trainer: str, transports: Sequence[str]
    ) -> ChannelOffer | None:
        """A channel for ``trainer``'s rounds of ``group`` (which it holds alone): the first of
        ``transports`` (the trainer's, preferred first) this server offers and can make, sized
        for its current Steps; None: its rounds go over Zenoh (why is said in the log)."""
        self.open_for(trainer)
        self.forget_member(group.group_id, trainer)
        terms = ChannelTerms(
            trainer=trainer,
            ticket=group.members[trainer].ticket,
            current=group.current_steps(trainer),
            fallback=self._zenoh[trainer],
            on_ring=self._on_ring,
        )
        for transport in transports:
            make = self._makers.get(transport)
            if make is None:
                continue
            try:
                channel = make(terms)
            except OSError as error:
                log.warning("no %s channel for %s (trying the next): %s", transport, trainer, error)
                continue
            if channel is not None:
                self._offered[(trainer, group.group_id)] = channel
                return channel.offer()
        return None

    def offered_channel(self, trainer: str, group: int) -> OfferedChannel | None:
        """``trainer``'s offered channel of ``group``, if it has one."""
        return self._offered.get((trainer, group))

    def rung(self) -> list[OfferedChannel]:
        """The offered channels whose trainer put Actions since the loop took them."""
        return [channel for channel in self._offered.values() if channel.rung()]

    @contextlib.contextmanager
    def asleep(self) -> Iterator[None]:
        """While the service loop sleeps on its inbox: the offered channels hear their
        trainers' rings and enqueue them (``on_ring``). Awake, the loop looks at :meth:`rung`
        itself, and a ring wakes no thread: a woken thread would take the GIL from the loop's
        round, and its trainer's ring would pay the wake-up (bench/RESULTS.md, issue 70)."""
        channels = tuple(self._offered.values())
        for channel in channels:
            channel.hear_rings(True)
        try:
            yield
        finally:
            for channel in channels:
                channel.hear_rings(False)

    @property
    def has_offered(self) -> bool:
        return bool(self._offered)

    def actions_over_zenoh(self, trainer: str, group: int) -> None:
        """``trainer``'s Actions for ``group`` came over Zenoh: it does not take the channel it
        was offered (it chose Zenoh, could not reach it, or speaks an older protocol), so
        that channel goes."""
        self.forget_member(group, trainer)

    def send_steps(self, group: Group, trainer: str, steps: Message) -> None:
        """``trainer``'s Steps of a round of ``group`` (or what replaced them): through its
        offered channel where it has one and holds the group alone; a shared group steps on a
        deadline, which could overwrite a round a member is still reading, so there the round
        goes as what is not a round does (over Zenoh, rung in a segment all the same: its
        trainer sleeps on the bell)."""
        offered = self._offered.get((trainer, group.group_id))
        if offered is not None:
            if isinstance(steps, Steps) and len(group.members) == 1:
                offered.send_steps(steps)
            else:
                offered.send(steps)
            return
        channel = self._zenoh.get(trainer)
        if channel is None:
            send_once(self.session, self.server, trainer, steps)
        else:
            channel.send(steps)

    def send(self, trainer: str, message: Message) -> None:
        """What is not a round (an error reply): over Zenoh, and where it is about a group
        whose rounds go through an offered channel, through that channel's way for it."""
        group = message.group if isinstance(message, ErrorReply) else None
        channel: StepsChannel | None = None
        if group is not None:
            channel = self._offered.get((trainer, group))
        if channel is None:
            channel = self._zenoh.get(trainer)
        if channel is not None:
            channel.send(message)
        else:  # a trainer with no arenas here: no channel kept for it
            send_once(self.session, self.server, trainer, message)

    def forget_member(self, group: int, trainer: str) -> None:
        """Close ``trainer``'s offered channel of ``group`` (it left the group)."""
        channel = self._offered.pop((trainer, group), None)
        if channel is not None:
            channel.close()

    def close(self) -> None:
        """Close every channel (the server stops)."""
        self._forget_offered(lambda trainer, group: True)
        for channel in self._zenoh.values():
            channel.close()
        self._zenoh.clear()

    def forget_trainer(self, trainer: str) -> None:
        self._forget_offered(lambda held_by, group: held_by == trainer)
        channel = self._zenoh.pop(trainer, None)
        if channel is not None:
            channel.close()

    def _forget_offered(self, which: Callable[[str, int], bool]) -> None:
        for trainer, group in list(self._offered):
            if which(trainer, group):
                self.forget_member(group, trainer)

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
        self._forget_offered(lambda trainer, group_id: group_id == group.group_id)
        for arena in group.arena_ids:
            pub = self._world_pubs.pop(arena, None)
            if pub is not None:
                pub.undeclare()
        self._last_world.pop(group.group_id, None)
