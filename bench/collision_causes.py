"""Where the other car was when the car decided its last lane change before each collision.

Reads episode records (``overtake-eval --episodes-out``, the experiments' evaluations, their
copies kept in ``bench/results/``), replays each collision episode in process from its seed and
recorded actions (the simulator is deterministic, as ``overtake-replay`` relies on), and, at the
decision of its first collision, finds the car the agent touched (the partner). It then goes back to
the agent's last lane change before the collision and says where the partner was when that
lane change was decided:

- ``in the target lane``, ``in the car's own lane``;
- ``two lanes over, already moving into the target lane`` (off its lane's centre towards the
  target by more than ``--drift-lanes``), or ``two lanes over, not yet moving``: both cars then
  change into the same lane from opposite sides;
- ``elsewhere``; and ``no lane change within N decisions`` where the car kept its lane.

The safety shield (``overtake.client.shield``) judges a lane change by the cars in the target
lane: this says which collisions its rule could not have seen coming. Figures, not times: it
may run beside anything.

    .venv/bin/python -m bench.collision_causes RECORD.jsonl [RECORD.jsonl ...] [--within 7]
"""

from __future__ import annotations

import collections
from dataclasses import dataclass
from pathlib import Path
from typing import Any

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

LANE_CHANGES = {"lane_left": +1, "lane_right": -1}  # lane index change (lanes count leftwards)


@dataclass(frozen=True)
class CausesConfig:
    records: Positional[tuple[Path, ...]]
    """episode records (.jsonl); only their episodes with a collision are replayed"""
    within: int = 7
    """a lane change further back than this many decisions before the collision is not its
    cause"""
    drift_lanes: float = 0.05
    """how far (in lane widths) off its lane's centre towards the target lane a car two lanes
    over must be to count as already moving into it"""


@dataclass(frozen=True)
class Cause:
    """One collision: the episode, the decision it happened at, and where the partner was."""

    record: str
    episode: int
    collision_decision: int
    lane_change_decision: int | None
    where: str
    partner_dx_m: float | None
    """the partner's position ahead of the car (m) when the lane change was decided"""
    partner_dv_kmh: float | None
    """the partner's speed minus the car's (km/h) then"""


def _frames(header: RecordHeader, episode: EpisodeRecord, until: int) -> list[Any]:
    """The road before each decision up to ``until`` and after it, replayed; raises where the
    replay has no collision at ``until`` (the record's)."""
    envs = make_vector_env(header.preset, header.overrides, 1, None)
    try:
        env = envs.unwrapped
        obs, info = envs.reset(seed=[episode.seed])
        counts = EventCounts(1)
        counts.rose(info)

        def frame(obs: dict[str, np.ndarray]) -> Any:
            return env.world_frame(0, {k: v[0] for k, v in obs.items()}, 0.0, -1, {})

        frames = [frame(obs)]
        for decision, action in enumerate(episode.action_array()[: until + 1]):
            obs, _, _, _, info = envs.step(np.array([action]))
            frames.append(frame(obs))
            collided = bool(counts.rose(info).get("collisions", np.zeros(1, bool))[0])
            if collided != (decision == until):
                raise RuntimeError(
                    f"episode {episode.episode} replays with "
                    f"{'a' if collided else 'no'} collision at decision {decision}, unlike its "
                    "record (another simulator than the record's?)"
                )
    finally:
        envs.close()
    return frames


def where_was(own_lanes: float, partner_lanes: float, direction: int, drift_lanes: float) -> str:
    """Where the partner was when the car decided a lane change in ``direction`` (+1 left, -1
    right): positions across the road in lane widths (lane k's centre at k + 0.5)."""
    own = int(np.floor(own_lanes))
    target = own + direction
    theirs = int(np.floor(partner_lanes))
    if theirs == target:
        return "in the target lane"
    if theirs == own:
        return "in the car's own lane"
    if theirs == target + direction:
        # Off its centre towards the target lane: its own lane change has begun.
        moving = (theirs + 0.5 - partner_lanes) * direction > drift_lanes
        return f"two lanes over, {'already' if moving else 'not yet'} moving into the target lane"
    return "elsewhere"


def cause(record: str, header: RecordHeader, episode: EpisodeRecord, config: CausesConfig) -> Cause:
    """Replay ``episode`` up to its first collision and say where the partner car was."""
    collided = episode.events["collisions"][0]
    frames = _frames(header, episode, collided)
    actions = episode.action_array()[: collided + 1]
    after = frames[-1]
    partners = [int(v) for v in touching(after) if v != 0]
    names = [ACTION_NAMES[int(a)] for a in actions]
    changes = [d for d in range(len(names)) if names[d] in LANE_CHANGES]
    if not changes or collided - changes[-1] > config.within:
        where = f"no lane change within {config.within} decisions"
        return Cause(record, episode.episode, collided, None, where, None, None)
    if not partners:
        return Cause(record, episode.episode, collided, None, "no other car", None, None)
    decided = changes[-1]
    before = frames[decided]
    partner = partners[0]
    lanes = before.y_m / before.lane_width_m
    where = where_was(lanes[0], lanes[partner], LANE_CHANGES[names[decided]], config.drift_lanes)
    return Cause(
        record,
        episode.episode,
        collided,
        decided,
        where,
        float(before.x_m[partner] - before.x_m[0]),
        float(before.speed_mps[partner] - before.speed_mps[0]) * 3.6,
    )


def main(config: CausesConfig) -> list[Cause]:
    causes: list[Cause] = []
    for path in config.records:
        header, episodes = read_records(path)
        for episode in episodes:
            if episode.collisions:
                found = cause(str(path), header, episode, config)
                causes.append(found)
                ahead = (
                    f", {found.collision_decision - found.lane_change_decision} decisions after "
                    f"the lane change; partner {found.partner_dx_m:+.1f} m ahead, "
                    f"{found.partner_dv_kmh:+.1f} km/h"
                    if found.lane_change_decision is not None
                    else ""
                )
                print(f"{path} episode {episode.episode}: {found.where}{ahead}")
    print("\n| where the other car was | collisions |\n|---|---:|")
    for where, count in collections.Counter(c.where for c in causes).most_common():
        print(f"| {where} | {count} |")
    print(f"| all | {len(causes)} |")
    return causes


if __name__ == "__main__":
    main(tyro.cli(CausesConfig))
