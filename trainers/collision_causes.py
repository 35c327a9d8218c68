"""``overtake-collision-causes``: where the other car was when the car decided its last lane
change before each collision, and which rule would have caught it.

Reads episode records (``overtake-eval --episodes-out``, the experiments' evaluations, their
copies kept in ``bench/results/``), replays each collision episode in process from its seed and
recorded actions up to its first collision (the simulator is deterministic, as
``overtake-replay`` relies on; a replay that does not meet the recorded collision is refused),
and finds the car the agent touched there (the partner). It then goes back to the last lane
change the agent made (the action applied, not only sent) within ``--within-decisions`` before
the collision, and says where the partner was when that change was decided, from the
simulator's own lane state:

- ``in the target lane``, ``in the car's own lane``;
- ``two lanes over, already changing into the target lane`` (its own lane change under way),
  or ``two lanes over, not yet changing into the target lane`` (it began later): both cars
  then change into the same lane from opposite sides;
- ``elsewhere``; ``no lane change within N decisions`` where the car kept its lane; ``no
  other car``.

The safety shield (``overtake.client.policies.shield``) judges a lane change by the cars in the
target lane: this says which collisions its rule could not have seen coming.

Which rule would have caught it: each collision episode is replayed again, from its seed and
recorded actions, under each rule in turn (:data:`RULES`): the decision shield (where it
forbids the recorded action, judged as a trainer judges it on the last two LIDAR scans and the
ego vector, the car keeps its lane instead), the lane-change watch
(``ego.lane_change_watch``: the simulator's driver assistance aborts or brakes through the
change), and both. A rule caught the collision where its replay has no collision up to
``--within-decisions`` after the record's: the first such rule is named, or "none of them".
The recorded actions go on after a rule changed one, so the replay is what the same driver
would have met for the next few seconds, not what a learner trained under the rule would do.
A rule the record's preset cannot have (the shield needs a LIDAR scan and the car's speed; the
watch, acceleration control) is left out, saying so. Figures, not times: it may run beside
anything.

    overtake-collision-causes RECORD.jsonl [RECORD.jsonl ...] [--out F.md]

The replay runs in this process, as ``overtake-replay``'s does by default: it reads the lane
state of the simulation core the in-process face offers (its ``sim``), which no world frame
carries (a car's target lane, its progress through a change).
"""

from __future__ import annotations

import collections
import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tyro.conf import Positional

from overtake.cli import Command, Output, UsageError
from overtake.client.episodes.recording import touching
from overtake.client.episodes.records import (
    EpisodeRecord,
    EventCounts,
    RecordError,
    RecordHeader,
    read_records,
)
from overtake.client.episodes.runner import VectorStep, run_episodes
from overtake.client.policies.shield import Shield
from overtake.protocol.vocabulary import (
    ACTION_NAMES,
    EPISODE_LENGTH_SETTING,
    KEEP,
    WATCH_SETTING,
)

from .episode_replay import RecordedActions, ReplayDiverged, replay_envs

# m/s in a km/h: the simulator's state holds speeds in m/s (its units module, which a trainer
# may not import, defines the same factor), the report says km/h.
MPS_PER_KMH = 1.0 / 3.6
# Lane index change of each lane-change action (lanes count leftwards, y grows with them).
LANE_CHANGE_DIRECTION = {"lane_left": +1, "lane_right": -1}
# The rules a collision is replayed under, in the order the report tries them: (the decision
# shield, the lane-change watch).
RULES: dict[str, tuple[bool, bool]] = {
    "the decision shield": (True, False),
    "the lane-change watch": (False, True),
    "shield and watch together": (True, True),
}
NO_RULE = "none of them"


@dataclass(frozen=True)
class CausesConfig:
    """Replay the collisions of episode records in this process: where the other car was at the
    car's last lane change before each, and which rule would have caught it."""

    records: Positional[tuple[Path, ...]]
    """episode records (.jsonl); only their episodes with a collision are replayed"""
    within_decisions: int = 7
    """a lane change further back than this many decisions before the collision is not its
    cause"""
    out: Path | None = None
    """also write the lines and the table here (Markdown)"""
    rules: bool = True
    """replay each collision under the decision shield, the lane-change watch and both, and
    name the first that avoids it (--no-rules: only where the other car was)"""

    def output_paths(self) -> tuple[Output, ...]:
        """What this command writes (checked before any episode is replayed)."""
        return (Output("--out", self.out),)


@dataclass(frozen=True)
class Road:
    """An arena's vehicles when a decision is taken (index 0: the agent)."""

    x_m: np.ndarray
    """(V,) position along the road"""
    speed_mps: np.ndarray
    """(V,)"""
    lane: np.ndarray
    """(V,) the lane a vehicle is in (its origin lane while it changes)"""
    target_lane: np.ndarray
    """(V,) the lane it is changing into (its lane where it is not changing)"""
    change_progress: np.ndarray
    """(V,) 0..1 through its lane change"""


@dataclass(frozen=True)
class Cause:
    """One collision: the episode, the decision it happened at, and where the partner was."""

    record: str
    episode: int
    collision_decision: int
    lane_change_decision: int | None
    where: str
    partner_ahead_m: float | None
    """the partner's position ahead of the agent when the lane change was decided"""
    partner_faster_kmh: float | None
    """the partner's speed minus the agent's then"""
    partner_change_progress: float | None
    """how far through its own lane change the partner was then (0..1; 0: not changing)"""
    caught_by: str = ""
    """the first of :data:`RULES` whose replay has no collision (:data:`NO_RULE`: none; empty:
    not asked)"""


@dataclass
class Replayed:
    """One episode replayed up to its first collision: the road before each decision, the
    actions applied, and the vehicles touching the agent after the colliding decision."""

    roads: list[Road]
    applied: list[int]
    touching_agent: np.ndarray | None = None


class _UntilCollision:
    """A watcher of :func:`~overtake.client.episodes.runner.run_episodes` over the recorded
    ``episodes`` (environment i plays episode i): keeps each one's roads and applied actions
    up to its record's first collision, and raises where the replay's collision is elsewhere."""

    def __init__(self, envs: Any, episodes: list[EpisodeRecord]) -> None:
        self.sim = envs.sim  # the in-process face's simulation core: the lanes' state
        self.episodes = episodes
        self.until = [episode.events["collisions"][0] for episode in episodes]
        self.replayed = [Replayed([], []) for _ in episodes]
        self.counts = EventCounts(len(episodes))

    def _road(self, arena: int) -> Road:
        state = self.sim.state
        return Road(
            state.x_m[arena].astype(np.float64),
            state.speed_mps[arena].astype(np.float64),
            state.lane[arena].copy(),
            state.target_lane[arena].copy(),
            state.change_progress[arena].astype(np.float64),
        )

    def started(self, obs: dict[str, np.ndarray], info: dict[str, Any]) -> None:
        self.counts.rose(info)
        for arena, replayed in enumerate(self.replayed):
            replayed.roads.append(self._road(arena))

    def stepped(self, step: VectorStep) -> None:
        info = step.info
        collided = self.counts.rose(info).get("collisions", np.zeros(len(self.episodes), bool))
        for arena, replayed in enumerate(self.replayed):
            decision, until = len(replayed.applied), self.until[arena]
            if decision > until:
                continue  # past its collision: the episode has ended, or goes on unwatched
            replayed.roads.append(self._road(arena))
            replayed.applied.append(int(info["action_applied"][arena]))
            if bool(collided[arena]) != (decision == until):
                raise ReplayDiverged(
                    f"episode {self.episodes[arena].episode} replays with "
                    f"{'a' if collided[arena] else 'no'} collision at decision {decision}, "
                    "unlike its record (another simulator than the record's?)"
                )
            if step.ended[arena] and decision < until:
                raise ReplayDiverged(
                    f"episode {self.episodes[arena].episode} ends at decision {decision}, "
                    f"before its record's collision at {until}"
                )
            if decision == until:
                replayed.touching_agent = touching(self.sim.world_snapshot(arena))


def replay(record: str, header: RecordHeader, episodes: list[EpisodeRecord]) -> list[Replayed]:
    """Replay ``episodes`` of ``record`` (each with a collision) together, from their seeds and
    recorded actions (:class:`~overtake.trainers.episode_replay.RecordedActions`), each up to
    its record's first collision; raises where a replay's collision is not where the record's
    is."""
    for episode in episodes:
        collisions = episode.events.get("collisions", ())
        if not collisions:
            raise RecordError(
                f"{record} episode {episode.episode} counts {episode.collisions} collisions but "
                "its record names no decision for them (a record older than the events?)"
            )
        if collisions[0] >= len(episode.actions):
            raise RecordError(
                f"{record} episode {episode.episode} has {len(episode.actions)} recorded "
                f"actions, its record's collision is at decision {collisions[0]}"
            )
    envs = replay_envs(header, len(episodes))
    watcher = _UntilCollision(envs, episodes)
    try:
        recorded = RecordedActions(episodes, None, False, header)
        run_episodes(envs, recorded, len(episodes), [e.seed for e in episodes], watchers=[watcher])
    finally:
        envs.close()
    return watcher.replayed


def where_was(road: Road, partner: int, direction: int) -> str:
    """Where ``partner`` was on ``road`` when the agent decided a lane change in ``direction``
    (+1 left, -1 right)."""
    own = int(road.lane[0])
    target = own + direction
    theirs = int(road.lane[partner])
    if theirs == target:
        return "in the target lane"
    if theirs == own:
        return "in the car's own lane"
    if theirs == target + direction:
        already = int(road.target_lane[partner]) == target
        return (
            f"two lanes over, {'already' if already else 'not yet'} changing into the target lane"
        )
    return "elsewhere"


def classify(
    record: str, episode: EpisodeRecord, replayed: Replayed, within_decisions: int
) -> Cause:
    """Where ``episode``'s partner car was, from its replay up to its first collision."""
    collision_decision = len(replayed.applied) - 1
    touching_agent = replayed.touching_agent
    partners = [] if touching_agent is None else [int(v) for v in touching_agent if v != 0]
    names = [ACTION_NAMES[a] if a >= 0 else "" for a in replayed.applied]
    changes = [d for d, name in enumerate(names) if name in LANE_CHANGE_DIRECTION]
    if not partners:
        where = "no other car"
    elif not changes or collision_decision - changes[-1] > within_decisions:
        where = f"no lane change within {within_decisions} decisions"
    else:
        lane_change_decision = changes[-1]
        before = replayed.roads[lane_change_decision]
        partner = partners[0]
        direction = LANE_CHANGE_DIRECTION[names[lane_change_decision]]
        return Cause(
            record,
            episode.episode,
            collision_decision,
            lane_change_decision,
            where_was(before, partner, direction),
            float(before.x_m[partner] - before.x_m[0]),
            float(before.speed_mps[partner] - before.speed_mps[0]) / MPS_PER_KMH,
            float(before.change_progress[partner]),
        )
    return Cause(record, episode.episode, collision_decision, None, where, None, None, None)


def cause(
    record: str, header: RecordHeader, episode: EpisodeRecord, within_decisions: int
) -> Cause:
    """Replay ``episode`` up to its first collision and say where the partner car was."""
    [replayed] = replay(record, header, [episode])
    return classify(record, episode, replayed, within_decisions)


class _ShieldedRecording:
    """The recorded actions, where the decision shield forbids one keeping the lane instead:
    judged on the last two LIDAR scans (restarted with each episode) and the ego vector, as a
    trainer's stacked frames give them."""

    def __init__(self, recorded: RecordedActions, shield: Shield) -> None:
        self.recorded, self.shield = recorded, shield
        self.previous: np.ndarray | None = None

    def __call__(
        self, obs: dict[str, np.ndarray], info: dict[str, Any], starting: np.ndarray
    ) -> np.ndarray:
        actions = self.recorded(obs, info, starting)
        scan = np.asarray(obs["lidar"], dtype=np.float64)
        if self.previous is None:
            self.previous = scan.copy()
        self.previous[np.asarray(starting, dtype=bool)] = scan[np.asarray(starting, dtype=bool)]
        allowed = self.shield.mask(np.stack([self.previous, scan], axis=1), obs["ego"])
        self.previous = scan.copy()
        forbidden = allowed[np.arange(len(actions)), actions] == 0
        return np.where(forbidden, KEEP, actions)


class _CollidesBy:
    """Per environment: whether its first episode collides at or before decision ``until``."""

    def __init__(self, until: list[int]) -> None:
        self.until = np.asarray(until, dtype=np.int64)
        self.counts = EventCounts(len(until))
        self.decision = np.zeros(len(until), dtype=np.int64)
        self.ended = np.zeros(len(until), dtype=bool)
        self.collided = np.zeros(len(until), dtype=bool)

    def started(self, obs: dict[str, np.ndarray], info: dict[str, Any]) -> None:
        self.counts.rose(info)

    def stepped(self, step: VectorStep) -> None:
        rose = self.counts.rose(step.info).get("collisions", np.zeros(len(self.until), bool))
        watched = ~self.ended & (self.decision <= self.until)
        self.collided |= rose & watched
        self.ended |= np.asarray(step.ended, bool)
        self.decision += 1


def rules_available(header: RecordHeader) -> tuple[dict[str, tuple[bool, bool]], list[str]]:
    """The rules a record's preset can be replayed under, and why the others cannot."""
    envs = replay_envs(header, 1)
    why: list[str] = []
    shield_ok = watch_ok = True
    try:
        try:
            Shield(envs.behaviour_spec)
        except ValueError as error:
            shield_ok = False
            why.append(f"no decision shield: {error}")
    finally:
        envs.close()
    try:
        replay_envs(header, 1, changes={WATCH_SETTING: True}).close()
    except ValueError as error:
        watch_ok = False
        why.append(f"no lane-change watch: {error}")
    rules = {
        name: (shield, watch)
        for name, (shield, watch) in RULES.items()
        if (shield_ok or not shield) and (watch_ok or not watch)
    }
    return rules, why


def caught_by(
    header: RecordHeader,
    episodes: list[EpisodeRecord],
    within_decisions: int,
    rules: dict[str, tuple[bool, bool]],
) -> list[str]:
    """For each of ``episodes`` (each with a collision), the first of ``rules`` under which
    its replay meets no collision up to ``within_decisions`` after its record's first, or
    :data:`NO_RULE`."""
    until = [episode.events["collisions"][0] + within_decisions for episode in episodes]
    found = [NO_RULE] * len(episodes)
    # The episodes end just past the window: what comes later is not looked at.
    recorded_length = header.config.get("episode", {}).get("max_decisions", max(until) + 2)
    window = {EPISODE_LENGTH_SETTING: min(recorded_length, max(until) + 2)}
    for name, (shielded, watched) in rules.items():
        envs = replay_envs(
            header, len(episodes), changes={**window, **({WATCH_SETTING: True} if watched else {})}
        )
        try:
            act: Any = RecordedActions(episodes, None, False, header)
            if shielded:
                act = _ShieldedRecording(act, Shield(envs.behaviour_spec))
            collides = _CollidesBy(until)
            run_episodes(envs, act, len(episodes), [e.seed for e in episodes], watchers=[collides])
        finally:
            envs.close()
        for index in np.flatnonzero(~collides.collided):
            if found[index] == NO_RULE:
                found[index] = name
    return found


def main(config: CausesConfig) -> list[Cause]:
    """Classify each collision of the records: prints a line for each and the tables (also to
    ``config.out``), and returns the causes."""
    if not config.records:
        raise UsageError("no episode records given: name one or more RECORD.jsonl")
    causes: list[Cause] = []
    lines: list[str] = []
    for path in config.records:
        header, episodes = read_records(path)
        crashed = [episode for episode in episodes if episode.collisions]
        replays = replay(str(path), header, crashed) if crashed else []
        rules, missing = rules_available(header) if crashed and config.rules else ({}, [])
        for why in missing:
            lines.append(f"- {path}: {why}")
            print(lines[-1])
        caught = caught_by(header, crashed, config.within_decisions, rules) if rules else []
        for index, (episode, replayed) in enumerate(zip(crashed, replays, strict=True)):
            found = classify(str(path), episode, replayed, config.within_decisions)
            if caught:
                found = dataclasses.replace(found, caught_by=caught[index])
            causes.append(found)
            detail = ""
            if found.lane_change_decision is not None:
                assert found.partner_ahead_m is not None and found.partner_faster_kmh is not None
                ahead, faster = found.partner_ahead_m, found.partner_faster_kmh
                detail = (
                    f", {found.collision_decision - found.lane_change_decision} decisions after "
                    f"the lane change; the partner {abs(ahead):.1f} m "
                    f"{'ahead' if ahead >= 0 else 'behind'}, {abs(faster):.1f} km/h "
                    f"{'faster' if faster >= 0 else 'slower'}, "
                    f"{found.partner_change_progress:.0%} through its own lane change"
                )
            if found.caught_by:
                detail += f"; caught by: {found.caught_by}"
            lines.append(f"- {path} episode {episode.episode}: {found.where}{detail}")
            print(lines[-1])
    table = ["", "| where the other car was | collisions |", "|---|---:|"]
    for where, count in collections.Counter(c.where for c in causes).most_common():
        table.append(f"| {where} | {count} |")
    table.append(f"| all | {len(causes)} |")
    asked = [c for c in causes if c.caught_by]
    if asked:
        table += ["", "| which rule would have caught it | collisions |", "|---|---:|"]
        for rule, count in collections.Counter(c.caught_by for c in asked).most_common():
            table.append(f"| {rule} | {count} |")
    print("\n".join(table))
    if config.out is not None:
        config.out.write_text("\n".join([*lines, *table]) + "\n", encoding="utf-8")
    return causes


COMMAND = Command("overtake-collision-causes", CausesConfig, main)


if __name__ == "__main__":
    COMMAND.run()
