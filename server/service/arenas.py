"""A server's arenas: the groups it holds, their arenas' server-wide ids, and who may open or
join more (the server's size and each trainer's share)."""

from __future__ import annotations

import heapq
import logging
import secrets
from collections.abc import Callable, Iterable

from overtake.protocol import errors
from overtake.protocol.messages import JoinRequest, Opened, OpenRequest

from .groups import Group

log = logging.getLogger("overtake.server")


def span(ids: list[int]) -> str:
    """Arena ids for a log line: ``3-7``, or ``1, 4, 9``, or ``none``."""
    if not ids:
        return "none"
    if len(ids) > 1 and ids == list(range(ids[0], ids[-1] + 1)):
        return f"{ids[0]}-{ids[-1]}"
    return ", ".join(map(str, ids))


class ArenaRegistry:
    """The groups of server ``server``: at most ``max_arenas`` arenas in all, and
    ``max_arenas_per_trainer`` per trainer (None: no share)."""

    def __init__(self, server: str, max_arenas: int, max_arenas_per_trainer: int | None) -> None:
        self.server = server
        self.max_arenas = max_arenas
        self.max_arenas_per_trainer = max_arenas_per_trainer
        self.groups: dict[int, Group] = {}
        self._arena_index: dict[int, tuple[int, int]] = {}  # arena id -> (group, index)
        self._next_arena = 0

    @property
    def used(self) -> int:
        return len(self._arena_index)

    def group(self, group_id: int) -> Group:
        group = self.groups.get(group_id)
        if group is None:
            raise errors.UnknownArena(
                f"server {self.server} has no group {group_id} (closed, or never opened)"
            )
        return group

    def open(self, request: OpenRequest, reply: Callable[[Group, str], Opened]) -> Opened:
        """A new group for ``request``, its arenas claimed by the asking trainer; registered
        only once ``reply(group, trainer)`` made the answer: a failure before leaves nothing
        behind."""
        self._check_share(request.trainer, request.arenas)
        free = self.max_arenas - self.used
        if request.arenas > free:
            raise errors.ServerFull(
                f"server {self.server} has {free} free arena(s) of "
                f"{self.max_arenas}, asked for {request.arenas}"
            )
        arena_ids = list(range(self._next_arena, self._next_arena + request.arenas))
        group = Group.open(
            self._new_group_id(),
            self.server,
            arena_ids,
            request.preset,
            dict(request.overrides),
            request.agents_per_arena,
            request.seed,
            request.as_recorded,
            request.observations,
            request.ego_fields,
            request.translation,
        )
        for index in range(request.arenas):
            group.claim(request.trainer, index, request.claim, fresh=True)
        opened = reply(group, request.trainer)
        self._next_arena += request.arenas
        self.groups[group.group_id] = group
        for index, arena in enumerate(arena_ids):
            self._arena_index[arena] = (group.group_id, index)
        log.info(
            "trainer %s opened group %d: %d arena(s) %s of %s, %d agent(s) each",
            request.trainer,
            group.group_id,
            request.arenas,
            span(arena_ids),
            request.preset,
            request.agents_per_arena,
        )
        return opened

    def join(self, request: JoinRequest, reply: Callable[[Group, str], Opened]) -> Opened:
        """The asking trainer's cars on an arena already open."""
        where = self._arena_index.get(request.arena)
        if where is None:
            raise errors.UnknownArena(
                f"server {self.server} has no arena {request.arena}; its "
                f"arenas are {span(sorted(self._arena_index))}"
            )
        group = self.groups[where[0]]
        member = group.members.get(request.trainer)
        if member is None or not member.slots[where[1]].any():
            self._check_share(request.trainer, 1)
        group.claim(request.trainer, where[1], request.agents, fresh=False)
        log.info(
            "trainer %s joined arena %d (group %d) with %d agent(s)",
            request.trainer,
            request.arena,
            group.group_id,
            request.agents,
        )
        return reply(group, request.trainer)

    def leave(self, group: Group, trainer: str, why: str) -> bool:
        """``trainer``'s cars leave ``group``; the group goes with its last member (True:
        its arenas are free)."""
        group.leave(trainer)
        if group.members:
            log.info(
                "trainer %s left group %d (%s); its cars are off the road",
                trainer,
                group.group_id,
                why,
            )
            return False
        self.groups.pop(group.group_id)
        for arena in group.arena_ids:
            self._arena_index.pop(arena, None)
        log.info(
            "trainer %s left group %d (%s); arenas %s freed after %d rounds",
            trainer,
            group.group_id,
            why,
            span(group.arena_ids),
            group.rounds_done,
        )
        return True

    def _arenas_of(self, trainer: str) -> int:
        """Arenas in which ``trainer`` holds cars."""
        return sum(
            int(member.slots.any(axis=1).sum())
            for group in self.groups.values()
            if (member := group.members.get(trainer)) is not None
        )

    def _check_share(self, trainer: str, more: int) -> None:
        limit = self.max_arenas_per_trainer
        if limit is None:
            return
        held = self._arenas_of(trainer)
        if held + more > limit:
            raise errors.ServerFull(
                f"server {self.server} lets one trainer hold at most {limit} arena(s) "
                f"(--max-arenas-per-trainer); {trainer} holds {held}, asked for {more} more"
            )

    def _new_group_id(self) -> int:
        # Random rather than counted: a restarted server never reuses the id of a group its
        # previous life served, so late messages about the old one cannot be mistaken.
        while True:
            group_id = secrets.randbelow(2**31)
            if group_id not in self.groups:
                return group_id


def ready_to_step(groups: Iterable[Group], now: float, limit: int) -> list[Group]:
    """Up to ``limit`` of the groups ready at ``now``, those stepped longest ago first. The
    server steps them (``limit``: its stepping threads) and handles what arrived before it
    picks again, so a group that became ready waits behind the groups that were ready before
    it and no longer. Stepping every ready group in a fixed order per pass let answers that
    arrive while a pass runs miss it in a fixed pattern: with the server busy, two of four
    equal trainers got exactly half the steps of the others."""
    return heapq.nsmallest(limit, (g for g in groups if g.ready(now)), key=lambda g: g.last_stepped)


def next_to_step(groups: Iterable[Group], now: float) -> Group | None:
    """Of the groups ready at ``now``, the one stepped longest ago (None: none is ready)."""
    chosen = ready_to_step(groups, now, 1)
    return chosen[0] if chosen else None
