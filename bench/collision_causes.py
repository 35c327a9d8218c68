"""Where the other car was when the car decided its last lane change before each collision.

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

The safety shield (``overtake.client.shield``) judges a lane change by the cars in the target
lane: this says which collisions its rule could not have seen coming. Figures, not times: it
may run beside anything.

    .venv/bin/python -m bench.collision_causes RECORD.jsonl [RECORD.jsonl ...] [--out F.md]
"""

from __future__ import annotations

import collections
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro
from tyro.conf import Positional

from overtake.client.episode_recording import touching
from overtake.client.episode_records import (
    EpisodeRecord,
    EventCounts,
    RecordHeader,
    read_records,
)
from overtake.client.episodes import make_vector_env
from overtake.protocol.vocabulary import ACTION_NAMES
from overtake.server.sim.units import KMH

# Lane index change of each lane-change action (lanes count leftwards, y grows with them).
LANE_CHANGE_DIRECTION = {"lane_left": +1, "lane_right": -1}


@dataclass(frozen=True)
class CausesConfig:
    records: Positional[tuple[Path, ...]]
    """episode records (.jsonl); only their episodes with a collision are replayed"""
    within_decisions: int = 7
    """a lane change further back than this many decisions before the collision is not its
    cause"""
    out: Path | None = None
    """also write the lines and the table here (Markdown)"""


@dataclass(frozen=True)
class Road:
    """Arena 0's vehicles when a decision is taken (index 0: the agent)."""

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
    touching_agent: np.ndarray
    """vehicles touching the agent (the agent among them), as the recordings colour them"""


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


def replay(
    header: RecordHeader, episode: EpisodeRecord, until: int
) -> tuple[list[Road], list[int]]:
    """The road before each decision up to ``until`` and after it (``until + 2`` roads), and
    the actions applied; raises where the replay's first collision is not at ``until``."""
    envs = make_vector_env(header.preset, header.overrides, 1, None)
    roads: list[Road] = []
    applied: list[int] = []
    try:
        sim = envs.unwrapped.sim
        _, info = envs.reset(seed=[episode.seed])
        counts = EventCounts(1)
        counts.rose(info)

        def road() -> Road:
            world = sim.world_snapshot(0)
            return Road(
                world.x_m,
                world.speed_mps.astype(np.float64),
                sim.state.lane[0].copy(),
                sim.state.target_lane[0].copy(),
                sim.state.change_progress[0].astype(np.float64),
                touching(world),
            )

        roads.append(road())
        for decision, action in enumerate(episode.action_array()[: until + 1]):
            _, _, _, _, info = envs.step(np.array([action]))
            roads.append(road())
            applied.append(int(info["action_applied"][0]))
            collided = bool(counts.rose(info).get("collisions", np.zeros(1, bool))[0])
            if collided != (decision == until):
                raise RuntimeError(
                    f"episode {episode.episode} replays with {'a' if collided else 'no'} "
                    f"collision at decision {decision}, unlike its record (another simulator "
                    "than the record's?)"
                )
    finally:
        envs.close()
    if len(applied) != until + 1:
        raise RuntimeError(
            f"episode {episode.episode} has {len(applied)} recorded actions, its record's "
            f"collision is at decision {until}"
        )
    return roads, applied


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


def cause(
    record: str, header: RecordHeader, episode: EpisodeRecord, within_decisions: int
) -> Cause:
    """Replay ``episode`` up to its first collision and say where the partner car was."""
    collisions = episode.events.get("collisions", ())
    if not collisions:
        raise RuntimeError(
            f"{record} episode {episode.episode} counts {episode.collisions} collisions but its "
            "record names no decision for them (a record older than the events?)"
        )
    collision_decision = collisions[0]
    roads, applied = replay(header, episode, collision_decision)
    partners = [int(v) for v in roads[-1].touching_agent if v != 0]
    names = [ACTION_NAMES[a] if a >= 0 else "" for a in applied]
    changes = [d for d, name in enumerate(names) if name in LANE_CHANGE_DIRECTION]
    if not partners:
        return Cause(
            record, episode.episode, collision_decision, None, "no other car", None, None, None
        )
    if not changes or collision_decision - changes[-1] > within_decisions:
        where = f"no lane change within {within_decisions} decisions"
        return Cause(record, episode.episode, collision_decision, None, where, None, None, None)
    lane_change_decision = changes[-1]
    before = roads[lane_change_decision]
    partner = partners[0]
    direction = LANE_CHANGE_DIRECTION[names[lane_change_decision]]
    return Cause(
        record,
        episode.episode,
        collision_decision,
        lane_change_decision,
        where_was(before, partner, direction),
        float(before.x_m[partner] - before.x_m[0]),
        float(before.speed_mps[partner] - before.speed_mps[0]) / KMH,
        float(before.change_progress[partner]),
    )


def main(config: CausesConfig) -> list[Cause]:
    causes: list[Cause] = []
    lines: list[str] = []
    for path in config.records:
        header, episodes = read_records(path)
        for episode in episodes:
            if not episode.collisions:
                continue
            found = cause(str(path), header, episode, config.within_decisions)
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
            lines.append(f"- {path} episode {episode.episode}: {found.where}{detail}")
            print(lines[-1])
    table = ["", "| where the other car was | collisions |", "|---|---:|"]
    for where, count in collections.Counter(c.where for c in causes).most_common():
        table.append(f"| {where} | {count} |")
    table.append(f"| all | {len(causes)} |")
    print("\n".join(table))
    if config.out is not None:
        config.out.write_text("\n".join([*lines, *table]) + "\n", encoding="utf-8")
    return causes


if __name__ == "__main__":
    main(tyro.cli(CausesConfig))
