"""What the server sends: each trainer's Steps (and error replies) on its own key, with blocking
congestion control so that no step is silently lost, and each watched arena's world frames
for spectators, dropped under congestion so that watching never holds the simulation back.

A trainer on this host that asked for it gets its Steps through a shared-memory segment
(:mod:`overtake.protocol.shared_memory`) and only a small notice on its key. The outbox owns
the segments: one per group a trainer holds alone, removed when the trainer leaves the group,
goes away or the server closes."""

from __future__ import annotations

import logging

import numpy as np
import zenoh

from overtake.protocol import codec, keys
from overtake.protocol.messages import Message, ShmArray, ShmOffer, Steps, StepsInShm
from overtake.protocol.shared_memory import Segment, layout_bytes
from overtake.protocol.shm_messages import OBSERVATION_PREFIX, STEPS_ARRAYS

from .groups import Group

log = logging.getLogger(__name__)


def steps_arrays(steps: Steps) -> dict[str, np.ndarray]:
    """A Steps' arrays by the names a notice gives them."""
    arrays = {name: getattr(steps, name) for name in STEPS_ARRAYS}
    arrays.update({OBSERVATION_PREFIX + k: v for k, v in steps.observations.items()})
    return arrays


class Outbox:
    """The server's publishers on its Zenoh ``session``."""

    def __init__(self, session: zenoh.Session, server: str, world_rate_hz: float) -> None:
        self.session, self.server = session, server
        self.world_rate_hz = world_rate_hz
        self._step_pubs: dict[str, zenoh.Publisher] = {}
        self._world_pubs: dict[int, zenoh.Publisher] = {}
        self._last_world: dict[int, float] = {}
        # (trainer, group id) -> its segment, and whether the trainer's latest Actions for the
        # group said it reads it.
        self._segments: dict[tuple[str, int], Segment] = {}
        self._reads_shm: dict[tuple[str, int], bool] = {}

    # --- shared memory ------------------------------------------------------------------------

    def offer_segment(self, group: Group, trainer: str) -> ShmOffer | None:
        """A segment for ``trainer``'s Steps of ``group`` (which it holds alone), sized for
        its current Steps; None where one cannot be made (said in the log)."""
        current = group.current_steps(trainer)
        arrays = steps_arrays(current)
        size = layout_bytes((value.dtype, value.shape) for value in arrays.values())
        try:
            segment = Segment.create(size)
        except OSError as error:
            log.warning("no shared memory for %s (Steps go over Zenoh): %s", trainer, error)
            return None
        self.forget_member(group.group_id, trainer)
        self._segments[(trainer, group.group_id)] = segment
        return ShmOffer(name=segment.name, nonce=segment.nonce, size_bytes=segment.size)

    def reads_shm(self, trainer: str, group: int, reads: bool) -> None:
        """``trainer`` said (in its latest Actions for ``group``) whether it reads the segment.

        Once it has said, the segment's name goes: the name was only for the trainer to find
        it, and both sides keep it mapped, so that nothing is left in /dev/shm however either
        of them ends (SIGKILL included)."""
        segment = self._segments.get((trainer, group))
        if segment is not None:
            self._reads_shm[(trainer, group)] = reads
            segment.unlink()

    def send_steps(self, group: Group, trainer: str, steps: Message) -> None:
        """``trainer``'s Steps of a round of ``group``: through its segment, where it reads one
        and holds the group alone (a shared group steps on a deadline, which could overwrite
        a round a member is still reading), else on its key."""
        key = (trainer, group.group_id)
        segment = self._segments.get(key)
        if (
            segment is not None
            and isinstance(steps, Steps)
            and self._reads_shm.get(key)
            and len(group.members) == 1
        ):
            written = segment.write(steps_arrays(steps))
            if written is not None:
                generation, places = written
                # Built from the server's own arrays every round: unchecked, as its Steps are
                # (the trainer checks the notice it decodes, and the arrays it reads).
                notice = StepsInShm.trusted(
                    server=steps.server,
                    group=steps.group,
                    round=steps.round,
                    generation=generation,
                    arrays=tuple(
                        ShmArray.trusted(name=n, offset=o, dtype=d, shape=sh)
                        for n, o, d, sh in places
                    ),
                )
                self.send(trainer, notice)
                return
        self.send(trainer, steps)

    def forget_member(self, group: int, trainer: str) -> None:
        """Remove ``trainer``'s segment of ``group`` (it left the group)."""
        self._reads_shm.pop((trainer, group), None)
        segment = self._segments.pop((trainer, group), None)
        if segment is not None:
            segment.unlink()
            segment.close()

    def close(self) -> None:
        """Remove every segment (the server stops)."""
        for trainer, group in list(self._segments):
            self.forget_member(group, trainer)

    # --- Zenoh ----------------------------------------------------------------------------------

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
        for held_by, group in list(self._segments):
            if held_by == trainer:
                self.forget_member(group, trainer)
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
        """The group's arenas are freed: their world publishers and segments go."""
        for trainer, group_id in list(self._segments):
            if group_id == group.group_id:
                self.forget_member(group_id, trainer)
        for arena in group.arena_ids:
            pub = self._world_pubs.pop(arena, None)
            if pub is not None:
                pub.undeclare()
        self._last_world.pop(group.group_id, None)
