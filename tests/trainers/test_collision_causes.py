"""overtake-collision-causes (overtake.trainers.collision_causes): where the other car of each
recorded collision was when the car decided its last lane change, from a replay that must meet
the record's collision."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from overtake.client.episodes.drive import DriveConfig
from overtake.client.episodes.drive import main as drive
from overtake.client.episodes.records import read_records
from overtake.client.episodes.scenario import Scenario
from overtake.trainers.collision_causes import (
    COMMAND,
    NO_RULE,
    RULES,
    CausesConfig,
    Road,
    caught_by,
    cause,
    main,
    rules_available,
    where_was,
)
from overtake.trainers.episode_replay import ReplayDiverged

ROOT = Path(__file__).resolve().parents[2]


def _road(partner_lane: int, partner_target_lane: int, own_lane: int = 2) -> Road:
    return Road(
        x_m=np.array([100.0, 101.0]),
        speed_mps=np.array([20.0, 18.0]),
        lane=np.array([own_lane, partner_lane]),
        target_lane=np.array([own_lane, partner_target_lane]),
        change_progress=np.array([0.0, 0.0 if partner_target_lane == partner_lane else 0.2]),
    )


@pytest.mark.parametrize(
    ("partner_lane", "partner_target", "direction", "expected"),
    [
        (3, 3, +1, "in the target lane"),
        (3, 4, +1, "in the target lane"),  # leaving it: still there when the agent decided
        (2, 2, +1, "in the car's own lane"),
        (4, 4, +1, "two lanes over, not yet changing into the target lane"),
        (4, 3, +1, "two lanes over, already changing into the target lane"),
        (4, 5, +1, "two lanes over, not yet changing into the target lane"),  # moving away
        (0, 1, -1, "two lanes over, already changing into the target lane"),
        (0, 0, -1, "two lanes over, not yet changing into the target lane"),
        (1, 1, -1, "in the target lane"),
        (0, 1, +1, "elsewhere"),  # two lanes over, on the other side
        (5, 4, +1, "elsewhere"),
    ],
)
def test_the_partner_is_placed_relative_to_the_target_lane(
    partner_lane, partner_target, direction, expected
):
    assert where_was(_road(partner_lane, partner_target), 1, direction) == expected


# The retired min2018-safe-both's medium episode 96 (its record's collisions, kept as test data
# when the experiment was retired, issue 56): the agent changed right at decision 1 and
# collided at decision 4 with a car that had begun to change left from two lanes over, 3.6 m
# ahead of it and 15.5 km/h slower when the agent decided (the preset before issue 44).
KEPT_RECORD = ROOT / "tests/trainers/data/min2018-safe-both-all-both-medium.jsonl"


def _kept_episode_96():
    header, episodes = read_records(KEPT_RECORD)
    [episode] = [e for e in episodes if e.episode == 96]
    return header, episode


def test_a_kept_collision_behind_the_shield_is_two_cars_meeting_in_one_lane():
    header, episode = _kept_episode_96()
    found = cause(str(KEPT_RECORD), header, episode, within_decisions=7)
    assert (found.lane_change_decision, found.collision_decision) == (1, 4)
    assert found.where == "two lanes over, already changing into the target lane"
    assert found.partner_ahead_m == pytest.approx(3.6, abs=0.05)
    assert found.partner_faster_kmh == pytest.approx(-15.5, abs=0.05)


def test_the_lane_watch_would_have_caught_the_two_cars_meeting_in_one_lane():
    # The same episode replayed under each rule: the record's driver already had the decision
    # shield in front of it, so that rule alone meets the same collision; the lane-change watch
    # aborts or brakes through the change and the collision is gone.
    header, episode = _kept_episode_96()
    rules, missing = rules_available(header)
    assert rules == RULES and missing == []
    assert caught_by(header, [episode], 7, {"shield": RULES["the decision shield"]}) == [NO_RULE]
    assert caught_by(header, [episode], 7, rules) == ["the lane-change watch"]


def test_a_rule_the_preset_cannot_have_is_left_out_saying_why(tmp_path):
    # ho2018 observes an occupancy grid (no LIDAR scan for the shield) and steps its speed
    # (no acceleration for the watch's brake): neither rule can be replayed there.
    drive(
        DriveConfig(
            policy="rule",  # type: ignore[arg-type]
            episodes=1,
            seed=0,
            episodes_out=tmp_path,
            scenario=Scenario(preset="ho2018", max_decisions=5),
        )
    )
    [path] = list(tmp_path.glob("*.jsonl"))
    header, _ = read_records(path)
    rules, missing = rules_available(header)
    assert rules == {}
    assert any("no decision shield" in why and "LIDAR" in why for why in missing), missing
    assert any("no lane-change watch" in why for why in missing), missing


def _record(out: Path) -> Path:
    # A random driver in heavy traffic: some of its short episodes end in a collision.
    drive(
        DriveConfig(
            policy="random",  # type: ignore[arg-type]
            episodes=8,
            seed=3,
            episodes_out=out,
            scenario=Scenario(
                preset="min2018",
                max_decisions=400,
                set=("traffic.density=heavy", "ego.lane_change_check=false"),
            ),
        )
    )
    [path] = list(out.glob("*.jsonl"))
    return path


def test_each_collision_is_replayed_to_its_recorded_decision(tmp_path, capsys):
    record = _record(tmp_path)
    _, episodes = read_records(record)
    crashed = {e.episode: e.events["collisions"][0] for e in episodes if e.collisions}
    assert crashed, "the random driver should collide in heavy traffic"
    out = tmp_path / "causes.md"
    causes = main(CausesConfig(records=(record,), out=out, rules=False))
    assert {c.episode: c.collision_decision for c in causes} == crashed
    assert f"| all | {len(crashed)} |" in capsys.readouterr().out
    written = out.read_text()
    assert f"| all | {len(crashed)} |" in written
    assert all(f"episode {c.episode}: {c.where}" in written for c in causes)

    # A record whose collision the replay does not meet is refused, not classified.
    lines = [json.loads(line) for line in record.read_text().splitlines()]
    first = next(line for line in lines[1:] if line["events"].get("collisions"))
    first["events"]["collisions"] = [first["events"]["collisions"][0] - 1]
    record.write_text("\n".join(json.dumps(line) for line in lines) + "\n")
    diverged = f"episode {first['episode']} replays with no collision"
    with pytest.raises(ReplayDiverged, match=diverged):
        main(CausesConfig(records=(record,)))
    # The command says so in one line, as every command does with what cannot be done.
    with pytest.raises(SystemExit) as exited:
        COMMAND.run([str(record), "--no-rules"])
    assert str(exited.value.code).startswith(f"overtake-collision-causes: {diverged}")


def test_an_out_that_cannot_be_written_is_refused_before_any_replay(tmp_path):
    def never(config):
        raise AssertionError("main ran: --out was not checked first")

    with pytest.raises(SystemExit) as exited:
        dataclasses.replace(COMMAND, main=never).run([str(KEPT_RECORD), "--out", str(tmp_path)])
    assert exited.value.code == (
        f"overtake-collision-causes: --out {tmp_path}: a folder is there, expected a file"
    )
