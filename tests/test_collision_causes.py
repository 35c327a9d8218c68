"""bench/collision_causes.py: where the other car of each recorded collision was when the car
decided its last lane change, from a replay that must meet the record's collision."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from bench.collision_causes import CausesConfig, main, where_was
from overtake.client.drive import DriveConfig
from overtake.client.drive import main as drive
from overtake.client.episode_records import read_records


@pytest.mark.parametrize(
    ("own", "partner", "direction", "expected"),
    [
        (2.5, 3.4, +1, "in the target lane"),
        (2.5, 2.9, +1, "in the car's own lane"),
        (2.5, 4.5, +1, "two lanes over, not yet moving into the target lane"),
        (2.5, 4.3, +1, "two lanes over, already moving into the target lane"),
        (2.5, 4.8, +1, "two lanes over, not yet moving into the target lane"),  # moving away
        (2.5, 0.7, -1, "two lanes over, already moving into the target lane"),
        (2.5, 0.5, -1, "two lanes over, not yet moving into the target lane"),
        (2.5, 1.2, -1, "in the target lane"),
        (2.5, 0.5, +1, "elsewhere"),  # two lanes over, on the other side
        (2.6, 5.5, +1, "elsewhere"),
    ],
)
def test_the_partner_is_placed_relative_to_the_target_lane(own, partner, direction, expected):
    assert where_was(own, partner, direction, drift_lanes=0.05) == expected


def _record(out: Path) -> Path:
    # A random driver in heavy traffic: some of its short episodes end in a collision.
    drive(
        DriveConfig(
            policy="random",  # type: ignore[arg-type]
            preset="min2018",
            episodes=8,
            seed=3,
            max_decisions=400,
            set=("traffic.density=heavy",),
            episodes_out=out,
        )
    )
    [path] = list(out.glob("*.jsonl"))
    return path


def test_each_collision_is_replayed_to_its_recorded_decision(tmp_path, capsys):
    record = _record(tmp_path)
    _, episodes = read_records(record)
    crashed = {e.episode: e.events["collisions"][0] for e in episodes if e.collisions}
    assert crashed, "the random driver should collide in heavy traffic"
    causes = main(CausesConfig(records=(record,)))
    assert {c.episode: c.collision_decision for c in causes} == crashed
    for found in causes:
        if found.lane_change_decision is not None:
            assert 0 <= found.collision_decision - found.lane_change_decision <= 7
    table = capsys.readouterr().out
    assert f"| all | {len(crashed)} |" in table

    # A record whose collision the replay does not meet is refused, not classified.
    lines = [json.loads(line) for line in record.read_text().splitlines()]
    first = next(line for line in lines[1:] if line["events"].get("collisions"))
    first["events"]["collisions"] = [first["events"]["collisions"][0] - 1]
    record.write_text("\n".join(json.dumps(line) for line in lines) + "\n")
    with pytest.raises(RuntimeError, match=f"episode {first['episode']} replays with no collision"):
        main(CausesConfig(records=(record,)))
