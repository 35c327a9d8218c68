"""Baseline drivers: the rule-based driver's decisions on scripted LIDAR scans, and random."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import gymnasium as gym
import numpy as np
import pytest

from overtake.cli import UsageError
from overtake.client import HIGHWAY_ENV_ID, RandomDriver, RuleDriver, RuleDriverConfig
from overtake.client.episodes.drive import COMMAND as drive_command
from overtake.client.episodes.drive import DriveConfig, main
from overtake.client.episodes.scenario import Scenario, parse_overrides
from overtake.protocol.vocabulary import (
    ACTION_COUNT,
    CRUISE_UP,
    EGO_FIELDS,
    KEEP,
    LANE_LEFT,
    LANE_RIGHT,
    METRIC_FIELDS,
)
from overtake.server.engine.env import HighwayEnv

from tests.support.scenes import LANE_WIDTH, Car, scripted_sim

RANGE = 80.0
# Min et al.'s ego vector, as min2018's behaviour spec names its columns.
MIN_EGO = HighwayEnv().behaviour_spec.observation("ego").columns
ALL_ALLOWED = np.ones((1, ACTION_COUNT), dtype=np.int8)


def scan(*points: tuple[float, float]) -> np.ndarray:
    """A (1, 360) LIDAR scan with nothing in range except hits at (x ahead, y left) points."""
    lidar = np.full((1, 360), RANGE, dtype=np.float32)
    for x, y in points:
        ray = round(math.degrees(math.atan2(y, x))) % 360
        lidar[0, ray] = min(lidar[0, ray], math.hypot(x, y))
    return lidar


def ego(
    speed_kmh: float = 80.0,
    warnings: tuple[bool, bool, bool] = (False, False, False),
    fields: tuple[str, ...] | None = None,
) -> np.ndarray:
    """A (1, E) ego vector of ``fields`` (min2018's by default): driving at ``speed_kmh`` (its
    cruise target too) in lane 2 of 5, not changing lanes, with the left, right and forward
    ``warnings``."""
    values = {
        "speed_mps": speed_kmh / 3.6,
        "cruise_target_mps": speed_kmh / 3.6,
        "lane_index": 2.0,
        "lane_count": 5.0,
        "lane_change_progress": 0.0,
        "lane_change_direction": 0.0,
        "left_warning": float(warnings[0]),
        "right_warning": float(warnings[1]),
        "forward_warning": float(warnings[2]),
        "ahead_distance_m": RANGE,
        "ahead_speed_mps": speed_kmh / 3.6,
    }
    return np.array([[values[name] for name in fields or MIN_EGO]], dtype=np.float32)


def mask(left: bool = True, right: bool = True) -> np.ndarray:
    allowed = np.ones((1, ACTION_COUNT), dtype=np.int8)
    allowed[0, LANE_LEFT], allowed[0, LANE_RIGHT] = left, right
    return allowed


def act(lidar: np.ndarray, ego_vector: np.ndarray | None = None, action_mask=ALL_ALLOWED) -> int:
    actions = RuleDriver(ego_fields=MIN_EGO).act(
        lidar, ego(80.0) if ego_vector is None else ego_vector, action_mask
    )
    assert actions.shape == (1,) and actions.dtype == np.int64
    return int(actions[0])


# --- cruise ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "speed_kmh, expected", [(40.0, CRUISE_UP), (75.0, CRUISE_UP), (79.9, CRUISE_UP), (80.0, KEEP)]
)
def test_rule_driver_accelerates_below_the_limit(speed_kmh, expected):
    assert act(scan(), ego(speed_kmh)) == expected


def test_rule_driver_does_not_accelerate_against_a_forward_warning():
    assert act(scan(), ego(60.0, warnings=(False, False, True))) == KEEP
    assert act(scan(), ego(60.0, warnings=(True, True, False))) == CRUISE_UP


def test_rule_driver_limit_follows_its_config():
    driver = RuleDriver(RuleDriverConfig(cruise_max_kmh=60.0), ego_fields=MIN_EGO)
    assert driver.act(scan(), ego(60.0), ALL_ALLOWED).tolist() == [KEEP]
    assert driver.act(scan(), ego(55.0), ALL_ALLOWED).tolist() == [CRUISE_UP]


def test_rule_driver_reads_a_cruise_target_where_the_ego_vector_has_one():
    # The remembered-target set-up: the target, not the speed, is what it raises.
    fields = EGO_FIELDS[:6]
    driver = RuleDriver(ego_fields=fields)
    slowed = ego(60.0, fields=fields)
    slowed[0, fields.index("cruise_target_mps")] = 80.0 / 3.6
    assert driver.act(scan(), slowed, ALL_ALLOWED).tolist() == [KEEP]
    assert driver.act(scan(), ego(60.0, fields=fields), ALL_ALLOWED).tolist() == [CRUISE_UP]
    with pytest.raises(ValueError, match="speed or cruise target"):
        RuleDriver(ego_fields=("left_warning",))


# --- lane changes ----------------------------------------------------------------------------


def test_free_distance_per_lane():
    driver = RuleDriver(ego_fields=MIN_EGO)
    free, clear = driver.free_distance(scan((20.0, 0.0), (50.0, LANE_WIDTH), (0.0, -2.6)))
    assert free[0].tolist() == pytest.approx([RANGE, 20.0, 50.0], abs=0.01)
    assert clear[0].tolist() == [False, True, True]  # the right has a car beside


def test_no_lane_change_on_a_free_road():
    assert act(scan()) == KEEP


def test_blocked_lane_with_free_neighbours_goes_left():
    # A car 20 m ahead in the own lane; both neighbours free: left on a tie.
    assert act(scan((20.0, 0.0))) == LANE_LEFT


def test_blocked_lane_goes_to_the_side_with_more_room():
    assert act(scan((20.0, 0.0), (40.0, LANE_WIDTH))) == LANE_RIGHT
    assert act(scan((20.0, 0.0), (40.0, -LANE_WIDTH))) == LANE_LEFT


def test_not_blocked_means_no_change():
    # 45 m ahead is more than blocked_ahead_m (40 m).
    assert act(scan((45.0, 0.0))) == KEEP


def test_a_neighbour_only_slightly_freer_is_not_worth_it():
    # Own lane free for 20 m; both neighbours free for 30 m < 20 + 15.
    assert act(scan((20.0, 0.0), (30.0, LANE_WIDTH), (30.0, -LANE_WIDTH))) == KEEP
    assert act(scan((20.0, 0.0), (36.0, LANE_WIDTH), (30.0, -LANE_WIDTH))) == LANE_LEFT


@pytest.mark.parametrize("beside_x", [0.0, 8.0, -12.0])
def test_no_change_towards_a_car_beside(beside_x):
    # A car in the left lane within [-15, 10] m of the ego: left is not safe; right is free.
    lidar = scan((20.0, 0.0), (beside_x, LANE_WIDTH - 0.9))
    assert act(lidar) == LANE_RIGHT
    lidar = scan((20.0, 0.0), (beside_x, LANE_WIDTH - 0.9), (beside_x, -(LANE_WIDTH - 0.9)))
    assert act(lidar) == KEEP


def test_car_well_behind_in_the_neighbour_lane_does_not_stop_the_change():
    assert act(scan((20.0, 0.0), (-25.0, LANE_WIDTH))) == LANE_LEFT


def test_no_change_towards_a_side_warning():
    blocked = scan((20.0, 0.0))
    assert act(blocked, ego(80.0, warnings=(True, False, True))) == LANE_RIGHT
    assert act(blocked, ego(80.0, warnings=(True, True, True))) == KEEP


def test_masked_lane_changes_are_never_chosen():
    lidar = scan((20.0, 0.0))
    assert act(lidar, action_mask=mask(left=False)) == LANE_RIGHT
    assert act(lidar, action_mask=mask(left=False, right=False)) == KEEP
    assert act(lidar, ego(60.0), mask(left=False, right=False)) == CRUISE_UP


@pytest.mark.parametrize("speed_kmh", [60.0, 80.0])
def test_rule_driver_on_sensor_scans_of_scripted_scenes(speed_kmh):
    # The same decisions from the simulator's own LIDAR (rails included) and ego vector
    # (warnings included); a lane change takes precedence over accelerating.
    def decide(cars, ego_lane=2):
        sim = scripted_sim(cars, ego_lane=ego_lane, ego_speed_kmh=speed_kmh)
        obs = sim.observe()
        return int(
            RuleDriver(ego_fields=MIN_EGO).act(
                obs["lidar"][:, 0], obs["ego"][:, 0], sim.action_mask()[:, 0]
            )[0]
        )

    free = CRUISE_UP if speed_kmh < 80.0 else KEEP
    # Behind a slow car (a forward warning at 60 km/h: within 2 s) it never accelerates.
    stuck = KEEP
    slow_ahead = Car(20.0, 2, 40.0)
    assert decide([]) == free
    assert decide([slow_ahead]) == LANE_LEFT
    assert decide([slow_ahead, Car(0.0, 3, 60.0)]) == LANE_RIGHT
    assert decide([slow_ahead, Car(0.0, 3, 60.0), Car(-5.0, 1, 60.0)]) == stuck
    assert decide([slow_ahead, Car(30.0, 3, 60.0), Car(30.0, 1, 60.0)]) == stuck
    assert decide([slow_ahead, Car(30.0, 3, 60.0), Car(40.0, 1, 60.0)]) == LANE_RIGHT
    # In the leftmost lane the only way is right; a car far enough ahead blocks nothing.
    assert decide([Car(20.0, 4, 40.0)], ego_lane=4) == LANE_RIGHT
    assert decide([Car(20.0, 0, 40.0), Car(0.0, 1, 60.0)], ego_lane=0) == stuck
    assert decide([Car(60.0, 2, 40.0)]) == free


def test_rule_driver_takes_batches():
    lidar = np.concatenate([scan(), scan((20.0, 0.0)), scan((20.0, 0.0))])
    egos = np.concatenate([ego(50.0), ego(80.0), ego(80.0)])
    masks = np.concatenate([ALL_ALLOWED, ALL_ALLOWED, mask(left=False)])
    assert RuleDriver(ego_fields=MIN_EGO).act(lidar, egos, masks).tolist() == [
        CRUISE_UP,
        LANE_LEFT,
        LANE_RIGHT,
    ]


# --- random ----------------------------------------------------------------------------------


def test_random_driver_picks_only_allowed_actions_and_all_of_them():
    driver = RandomDriver(seed=0)
    rng = np.random.default_rng(1)
    masks = (rng.random((2000, ACTION_COUNT)) < 0.6).astype(np.int8)
    masks[:, KEEP] = 1  # keep is always allowed
    actions = driver.act(np.zeros((2000, 360)), np.zeros((2000, 6)), masks)
    assert actions.shape == (2000,)
    assert masks[np.arange(2000), actions].all()
    assert set(actions.tolist()) == set(range(ACTION_COUNT))
    only_keep = np.zeros((50, ACTION_COUNT), dtype=np.int8)
    only_keep[:, KEEP] = 1
    assert (driver.act(np.zeros((50, 360)), np.zeros((50, 6)), only_keep) == KEEP).all()


def test_random_driver_is_reproducible_by_seed():
    masks = np.ones((100, ACTION_COUNT), dtype=np.int8)
    a = RandomDriver(seed=3).act(None, None, masks)
    b = RandomDriver(seed=3).act(None, None, masks)
    c = RandomDriver(seed=4).act(None, None, masks)
    assert np.array_equal(a, b) and not np.array_equal(a, c)


# --- the two against each other ----------------------------------------------------------------


def average_speeds(driver, episodes: int = 4, decisions: int = 300) -> np.ndarray:
    envs = gym.make_vec(
        HIGHWAY_ENV_ID,
        num_envs=episodes,
        vectorization_mode="vector_entry_point",
        overrides={
            "episode.max_decisions": decisions,
            "traffic.density": "medium",
            "camera.enabled": False,
        },
    )
    obs, info = envs.reset(seed=0)
    speeds = np.full(episodes, np.nan)
    while np.isnan(speeds).any():
        obs, _, terminated, truncated, info = envs.step(
            driver.act(obs["lidar"], obs["ego"], info["action_mask"])
        )
        for i in np.flatnonzero((terminated | truncated) & np.isnan(speeds)):
            speeds[i] = info["metrics"]["avg_speed_kmh"][i]
    return speeds


def test_rule_driver_is_faster_than_random():
    rule = average_speeds(RuleDriver(ego_fields=MIN_EGO))
    random = average_speeds(RandomDriver(seed=0))
    assert rule.mean() > random.mean() + 5.0
    assert (rule > 40.0).all() and (random >= 0.0).all()


# --- overtake-drive ----------------------------------------------------------------------------


@pytest.mark.parametrize("policy", ["rule", "random"])
def test_drive_cli_writes_the_summary(policy, tmp_path, capsys):
    out = tmp_path / "runs" / f"{policy}.json"
    summary = main(
        DriveConfig(
            policy=policy,
            episodes=2,
            seed=3,
            json_out=out,
            scenario=Scenario(
                max_decisions=12, traffic="light", set=("camera.width_px=16", "camera.height_px=16")
            ),
        )
    )
    data = json.loads(out.read_text())
    assert data["policy"] == policy and data["seed"] == 3 and data["preset"] == "min2018"
    assert data["overrides"] == {
        "camera.width_px": 16,
        "camera.height_px": 16,
        "traffic.density": "light",
        "episode.max_decisions": 12,
    }
    assert len(data["episodes"]) == 2
    assert data["summary"] == summary
    # Every metric of the contract (its names are pinned in tests/server/sim/test_rewards.py).
    assert set(summary) == set(METRIC_FIELDS)
    for name in METRIC_FIELDS:
        values = [episode[name] for episode in data["episodes"]]
        assert summary[name]["mean"] == pytest.approx(np.mean(values))
        assert summary[name]["std"] == pytest.approx(np.std(values))
    for episode in data["episodes"]:
        assert episode["decisions"] == 12 or episode["collisions"] == 1
        assert episode["avg_speed_kmh"] == pytest.approx(
            episode["distance_m"] / (episode["decisions"] * 0.4) * 3.6
        )
    printed = capsys.readouterr().out
    assert f"policy={policy}" in printed and "mean" in printed and "std" in printed


def test_drive_cli_refuses_bad_input():
    with pytest.raises(UsageError, match="episodes"):
        main(DriveConfig(episodes=0))
    with pytest.raises(UsageError, match="dotted.name=value"):
        parse_overrides(("no-equals-sign",))
    assert parse_overrides(("a.b=3", "c.d=heavy", "e.f=[1, 2]", "g=true")) == {
        "a.b": 3,
        "c.d": "heavy",
        "e.f": [1, 2],
        "g": True,
    }


def test_drive_command_prints_what_is_wrong_and_exits_non_zero():
    with pytest.raises(SystemExit) as exited:
        drive_command.run(["--episodes", "0"])
    assert exited.value.code == "overtake-drive: --episodes must be >= 1, got 0"
    # As a process: the in-process simulator refuses the override (its ConfigError, a
    # ValueError); the command says so in one line and exits with status 1, no traceback.
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "overtake.client.episodes.drive",
            "--episodes",
            "1",
            "--set",
            "no.such_field=1",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 1, done
    assert done.stderr.startswith("overtake-drive: unknown configuration field 'no.such_field'"), (
        done.stderr
    )
    assert "Traceback" not in done.stderr and not done.stdout


def test_the_rule_driver_s_refusal_names_the_references_that_drive_the_preset():
    from overtake.client.episodes.runner import baseline_policy

    env = HighwayEnv(preset="highway-fast")  # the Kinematics table alone: no LIDAR, no grid
    with pytest.raises(UsageError, match="--policy idm .*, random or idle instead$"):
        baseline_policy("rule", env.behaviour_spec, 0, 1)
    env.close()
    # Not a highway scene, and nothing the rule-based driver reads either.
    env = HighwayEnv(
        preset="min2018",
        overrides={"lidar.enabled": False, "ego_vector.enabled": False, "camera.enabled": True},
    )
    with pytest.raises(UsageError, match="--policy idle, random or planner .*or idm on"):
        baseline_policy("rule", env.behaviour_spec, 0, 1)
    env.close()


def test_the_idm_driver_collides_less_than_random_on_highway_fast(capsys):
    """--policy idm: highway-env's IDM + MOBIL car at the wheel, over the same seeded
    episodes as random (which crashes in nearly every one of highway-fast's episodes)."""
    scenario = Scenario(preset="highway-fast")
    idm = main(DriveConfig(policy="idm", episodes=6, seed=10, scenario=scenario))
    random = main(DriveConfig(policy="random", episodes=6, seed=10, scenario=scenario))
    assert idm["collisions"]["mean"] < random["collisions"]["mean"]
    assert idm["collisions"]["mean"] <= 1 / 6 and random["collisions"]["mean"] >= 0.5
    assert idm["decisions"]["mean"] > random["decisions"]["mean"]
    assert "policy=idm" in capsys.readouterr().out


def test_the_idm_driver_is_refused_where_there_is_no_highway_scene():
    from overtake.client.episodes.runner import policy_settings

    with pytest.raises(UsageError, match=r"presets highway-fast, highway\), not preset min2018"):
        main(DriveConfig(policy="idm", episodes=1, scenario=Scenario(preset="min2018")))
    assert policy_settings("idm", "highway", {}) == {"highway_scene.ego_driver": "idm"}
    assert policy_settings("rule", "highway", {}) == {}
