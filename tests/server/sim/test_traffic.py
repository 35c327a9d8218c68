"""Physics: car-following, traffic without overlaps, lane changes, actions and time."""

from __future__ import annotations

import numpy as np
import pytest

from overtake.protocol.vocabulary import AGENT_KIND
from overtake.server.sim import HighwaySim, make_config
from overtake.server.sim.physics import traffic_overlaps
from overtake.server.sim.traffic.kernels import idm as idm_accel
from overtake.server.sim.units import KMH

from tests.support.scenes import (
    HALF_LENGTH,
    LANE_WIDTH,
    ROAD_MAX,
    STEADY,
    Car,
    keep,
    lane_centre,
    place,
    scripted_sim,
)

MIN_GAP = 2.0
DECISION_S = 0.4


def bumper_gap(sim: HighwaySim, follower: int, leader: int) -> float:
    st = sim.state
    return float(st.x_m[0, leader] - st.x_m[0, follower] - 2 * HALF_LENGTH)


# --- car-following ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    "leader_kmh, follower_kmh, gap_m",
    [(50.0, 80.0, 40.0), (45.0, 80.0, 20.0), (60.0, 80.0, 10.0), (45.0, 65.0, 80.0)],
)
def test_traffic_follows_a_slower_leader_without_closing_below_min_gap(
    leader_kmh, follower_kmh, gap_m
):
    # The agent drives beside them at the leader's speed so that nobody is recycled.
    sim = scripted_sim(
        [
            Car(gap_m + 2 * HALF_LENGTH, 1, follower_kmh, desired_kmh=80.0),
            Car(2 * gap_m + 4 * HALF_LENGTH, 1, leader_kmh),
        ],
        ego_lane=3,
        ego_speed_kmh=leader_kmh,
        cruise_kmh=leader_kmh,
        # The agent holds the leader's speed, and the whole scene stays within range.
        overrides={"ego.cruise_mode": "remembered", "traffic.keep_ahead_m": 300.0},
    )
    gaps = []
    for _ in range(500):
        keep(sim)
        gaps.append(bumper_gap(sim, 1, 2))
    st = sim.state
    assert st.lane[0, 1:].tolist() == [1, 1] and st.active[0].all()  # the scene held
    assert min(gaps) >= MIN_GAP
    # The follower ends up at the leader's speed, at about its IDM equilibrium gap.
    assert st.speed_mps[0, 1] == pytest.approx(leader_kmh * KMH, rel=1e-3)
    equilibrium = MIN_GAP + leader_kmh * KMH * 1.5 / np.sqrt(1 - (leader_kmh / 80.0) ** 4)
    assert gaps[-1] == pytest.approx(equilibrium, rel=0.02)


def test_ego_cruise_control_follows_a_slower_leader_without_closing_below_min_gap():
    # A kept 80 km/h target: cruise control follows the leader's 50 km/h (with Min et al.'s
    # "current speed" actions the target would sink with the speed; see test_min2018.py).
    sim = scripted_sim(
        [Car(40.0, 2, 50.0)],
        ego_lane=2,
        ego_speed_kmh=80.0,
        cruise_kmh=80.0,
        overrides={"ego.cruise_mode": "remembered"},
    )
    gaps = []
    for _ in range(500):
        result = keep(sim)
        assert not result.terminated.any()
        gaps.append(bumper_gap(sim, 0, 1))
    assert min(gaps) >= MIN_GAP
    assert sim.state.speed_mps[0, 0] == pytest.approx(50.0 * KMH, rel=1e-3)
    # Cruise control keeps the IDM's desired gap at the leader's speed (headway 1.2 s): its
    # speed controller, not the IDM's free-road term, handles the cruise target.
    equilibrium = MIN_GAP + 50.0 * KMH * 1.2
    assert gaps[-1] == pytest.approx(equilibrium, rel=0.02)
    assert sim.metrics()["collisions"][0, 0] == 0


def test_idm_acceleration_formula():
    # Free road at the desired speed: no acceleration; half the desired speed: 15/16 of a_max.
    a = [idm_accel(v, 20.0, 1e9, 0.0, 1.5, 2.0, 1.5, 2 * np.sqrt(1.5 * 2.5)) for v in (20.0, 10.0)]
    assert a == pytest.approx([0.0, 1.5 * 15 / 16], abs=1e-9)
    # Far below the desired speed, exactly at the desired gap s* = s0 + v T behind an equally
    # fast leader: no acceleration; at half of it: a_max (1 - 4).
    gap = 2.0 + 10.0 * 1.5
    for factor, expected in ((1.0, 0.0), (0.5, -4.5)):
        a = idm_accel(10.0, 1e9, gap * factor, 0.0, 1.5, 2.0, 1.5, 3.0)
        assert a == pytest.approx(expected, abs=1e-9)
    # Closing in adds v * dv / (2 sqrt(a b)) to the desired gap.
    a = idm_accel(10.0, 1e9, gap + 10.0 * 3.0 / 3.0, 3.0, 1.5, 2.0, 1.5, 3.0)
    assert a == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize(
    "overrides, least_cars",
    [
        ({"traffic.density": "heavy"}, 17),
        # More cars than the kept 200 m hold at comfortable gaps: as many as fit, packed.
        ({"road.lane_count": 7, "traffic.vehicle_count": 90}, 40),
    ],
)
def test_heavy_traffic_never_overlaps(overrides, least_cars):
    # On the treadmill, which keeps the road full: the car-following and lane changes are on
    # trial, not the spawners (min2018's since issue 68), under which two cars that touch
    # leave the road at the end of the decision (test_spawners.py).
    arenas, decisions = 8, 400
    sim = HighwaySim(
        make_config(
            overrides={**overrides, "camera.enabled": False, "traffic.entry": "comfortable"}
        ),
        num_arenas=arenas,
    )
    sim.reset(seeds=list(range(100, 100 + arenas)))
    rng = np.random.default_rng(0)
    moved = 0
    for step in range(decisions):
        # The agents mostly keep their lane, now and then change speed or lane.
        actions = np.where(rng.random((arenas, 1)) < 0.8, 0, rng.integers(0, 5, (arenas, 1)))
        before = sim.state.lane.copy()
        result = sim.step(actions)
        moved += int((sim.state.lane[:, 1:] != before[:, 1:]).sum())
        overlaps = traffic_overlaps(sim.state, sim.kinds, sim.agents)
        assert overlaps.shape == (arenas,)
        assert not overlaps.any(), f"traffic overlaps {overlaps.tolist()} at decision {step}"
        ended = np.flatnonzero(result.terminated[:, 0] | result.truncated[:, 0])
        if ended.size:
            sim.reset(ended)
    # It was real traffic: full of cars that changed lanes.
    assert sim.state.active[:, 1:].sum(axis=1).min() >= least_cars
    assert moved > 50


def test_a_passive_agent_is_never_hit():
    # Agents that only keep their lane: traffic's lane changes are safe for them and their
    # cruise control and emergency braking keep them off the car ahead.
    arenas = 16
    sim = HighwaySim(
        make_config(overrides={"traffic.density": "medium", "camera.enabled": False}),
        num_arenas=arenas,
    )
    sim.reset(seeds=list(range(arenas)))
    for _ in range(250):
        result = keep(sim)
        assert not result.terminated.any()
    assert (sim.metrics()["collisions"] == 0).all()


@pytest.mark.parametrize("frames_per_decision", [1, 4])
def test_a_car_that_closes_into_the_agent_within_a_frame_collides_in_that_decision(
    frames_per_decision,
):
    # The car behind is 0.5 m off the agent's bumper and 140 km/h faster: after one frame's
    # move (0.1 s) the boxes overlap, before any gap of the arena was negative. Where that
    # frame is the decision's last (one frame a decision, as Ho's presets step), the decision
    # must end in the collision; the test once ran only where some gap of the batch was
    # already negative, and saw it a decision late, or, alone, never if the overlap ended.
    sim = scripted_sim(
        [Car(-2 * HALF_LENGTH - 0.5, 2, 200.0)],
        ego_lane=2,
        overrides={"episode.frames_per_decision": frames_per_decision},
    )
    result = keep(sim)
    assert result.terminated[0, 0]
    assert sim.metrics()["collisions"][0, 0] == 1


def test_traffic_overlaps_counts_overlapping_pairs():
    sim = scripted_sim([Car(30.0, 1, 60), Car(32.0, 1, 60), Car(33.0, 1, 60)])
    assert traffic_overlaps(sim.state, sim.kinds, sim.agents).tolist() == [3]
    sim.state.active[0, 3] = False
    assert traffic_overlaps(sim.state, sim.kinds, sim.agents).tolist() == [1]


# --- lane changes, masks and cruise ------------------------------------------------------------


@pytest.mark.parametrize("action, direction", [(3, 1), (4, -1)])
def test_lane_change_ends_centred_in_the_next_lane_after_two_seconds(action, direction):
    sim = scripted_sim([], ego_lane=2, overrides={"ego_vector.fields": ["lane_index"]})
    st = sim.state
    result = sim.step(np.array([[action]]))
    assert result.action_applied[0, 0] == action
    assert st.target_lane[0, 0] == 2 + direction
    ys = [float(st.y_m[0, 0])]
    for _ in range(3):
        keep(sim)
        ys.append(float(st.y_m[0, 0]))
    # 2 s = 5 decisions: still under way after 4 ...
    assert st.lane[0, 0] == 2 and st.target_lane[0, 0] == 2 + direction
    assert 0.0 < st.change_progress[0, 0] < 1.0
    # ... the y follows the minimum-jerk profile, monotonically ...
    for k, y in enumerate(ys, start=1):
        p = k * 0.2  # minimum jerk: 10 p^3 - 15 p^4 + 6 p^5
        expected = lane_centre(2) + direction * LANE_WIDTH * (10 * p**3 - 15 * p**4 + 6 * p**5)
        assert y == pytest.approx(expected, abs=1e-9)
    # ... and done after the fifth, exactly centred in the next lane.
    keep(sim)
    assert st.lane[0, 0] == st.target_lane[0, 0] == 2 + direction
    assert st.change_progress[0, 0] == 0.0
    assert st.y_m[0, 0] == lane_centre(2 + direction)
    keep(sim)
    assert st.y_m[0, 0] == lane_centre(2 + direction)
    assert sim.observe()["ego"][0, 0, 0] == 2 + direction


def test_lateral_action_during_a_change_is_ignored_and_masked():
    sim = scripted_sim([], ego_lane=2)
    st = sim.state
    assert sim.action_mask()[0, 0].tolist() == [1, 1, 1, 1, 1]
    sim.step(np.array([[3]]))
    assert sim.action_mask()[0, 0].tolist() == [1, 1, 1, 0, 0]
    for action in (3, 4, 3):
        result = sim.step(np.array([[action]]))
        assert result.action_applied[0, 0] == 0
        assert result.reward_terms["lane_change"][0, 0] == 0.0
        assert st.target_lane[0, 0] == 3
    keep(sim)
    assert st.lane[0, 0] == 3 and st.y_m[0, 0] == lane_centre(3)
    assert sim.action_mask()[0, 0].tolist() == [1, 1, 1, 1, 1]
    assert sim.metrics()["lane_changes"][0, 0] == 1


BODY = 2 * HALF_LENGTH  # centre to centre when two cars touch bumper to bumper
# Driver assistance that refuses a lane change against a side warning (min2018's, as the
# authors' code), with the action mask saying so (min2018's mask does not: its agent chooses
# among all five actions and the car refuses).
CHECKED = {"ego.lane_change_check": True, "ego.mask_refusals": True}


@pytest.mark.parametrize(
    "dx, clear",
    [
        (0.0, False),  # alongside
        (BODY + 1.9, False),
        (BODY + 2.1, True),  # ahead: 2 m bumper to bumper needed
        (-(BODY + 3.9), False),
        (-(BODY + 4.1), True),  # behind: 4 m needed
        (-(BODY - 1.0), False),  # overlapping from behind
    ],
)
def test_driver_assistance_starts_a_lane_change_only_into_a_clear_lane(dx, clear):
    sim = scripted_sim([Car(dx, 3, 60.0)], ego_lane=2, overrides=CHECKED)
    mask = sim.action_mask()[0, 0]
    assert mask[3] == clear
    assert mask[4] == 1  # the lane on the right is empty
    result = sim.step(np.array([[3]]))
    assert result.action_applied[0, 0] == (3 if clear else 0)
    assert result.reward_terms["lane_change"][0, 0] == (-0.25 if clear else 0.0)
    assert sim.state.target_lane[0, 0] == (3 if clear else 2)
    # The preset's own mask leaves the change to the car: it is offered, and refused.
    unmasked = scripted_sim([Car(dx, 3, 60.0)], ego_lane=2)
    assert unmasked.action_mask()[0, 0].tolist() == [1, 1, 1, 1, 1]
    assert unmasked.step(np.array([[3]])).action_applied[0, 0] == (3 if clear else 0)


def test_a_car_moving_into_the_target_lane_blocks_it_and_the_check_can_be_turned_off():
    for check in (True, False):
        sim = scripted_sim(
            [Car(0.0, 4, 60.0)],
            ego_lane=2,
            overrides={"ego.lane_change_check": check, "ego.mask_refusals": True},
        )
        sim.state.target_lane[0, 1] = 3  # the car two lanes over is moving into lane 3
        assert sim.action_mask()[0, 0, 3] == (0 if check else 1)
        assert sim.step(np.array([[3]])).action_applied[0, 0] == (0 if check else 3)


@pytest.mark.parametrize("speed_kmh, clear", [(60.0, True), (100.0, False)])
def test_a_faster_car_behind_needs_a_longer_gap(speed_kmh, clear):
    # 4.5 m bumper to bumper behind is enough for a car at the ego's speed; one 40 km/h faster
    # closes 11 m in the second the window grows by (lane_change_closing_time_s).
    sim = scripted_sim([Car(-(BODY + 4.5), 3, speed_kmh)], ego_lane=2, overrides=CHECKED)
    assert sim.action_mask()[0, 0, 3] == clear
    assert sim.step(np.array([[3]])).action_applied[0, 0] == (3 if clear else 0)


def test_stepping_some_arenas_checks_each_arenas_own_side():
    # Autoreset steps only the arenas not restarting: the check must read those arenas' state.
    sim = HighwaySim(make_config(overrides={"traffic.vehicle_count": 1, **CHECKED}), num_arenas=3)
    sim.reset(seeds=[0, 1, 2])
    for arena in range(3):
        place(sim, 0, x=0.0, lane=2, speed_kmh=60.0, kind=AGENT_KIND, arena=arena)
        # A car alongside in the left lane of arena 0 only; far away elsewhere.
        place(sim, 1, x=0.0 if arena == 0 else 300.0, lane=3, speed_kmh=60.0, arena=arena)
    before = sim.state.target_lane[1].copy()
    result = sim.step(np.array([[3], [3]]), arenas=np.array([0, 2]))
    assert result.action_applied[:, 0].tolist() == [0, 3]
    assert sim.state.target_lane[:, 0].tolist() == [2, before[0], 3]


def test_two_agents_cleared_into_one_gap_at_once_the_first_goes():
    sim = HighwaySim(
        make_config(overrides={"traffic.vehicle_count": 0, **CHECKED}),
        num_arenas=1,
        agents_per_arena=2,
    )
    sim.reset(seeds=[0])
    place(sim, 0, x=0.0, lane=1, speed_kmh=60.0, kind=AGENT_KIND)
    place(sim, 1, x=1.0, lane=3, speed_kmh=60.0, kind=AGENT_KIND)
    assert sim.action_mask()[0, :, 3:].tolist() == [[1, 1], [1, 1]]  # each alone is clear
    result = sim.step(np.array([[3, 4]]))
    assert result.action_applied[0].tolist() == [3, 0]
    assert sim.state.target_lane[0, :2].tolist() == [2, 3]


def test_cars_in_the_own_lane_or_two_lanes_over_do_not_block_a_change():
    sim = scripted_sim([Car(BODY + 0.5, 2, 60.0), Car(0.0, 0, 60.0), Car(0.0, 4, 60.0)], ego_lane=2)
    assert sim.action_mask()[0, 0].tolist() == [1, 1, 1, 1, 1]
    assert sim.lane_changes.side_clear(sim.state)[0, 0].tolist() == [True, True]


@pytest.mark.parametrize("lane, blocked", [(0, 4), (4, 3)])
def test_lateral_actions_are_masked_and_ignored_at_the_road_edges(lane, blocked):
    sim = scripted_sim([], ego_lane=lane)
    mask = sim.action_mask()[0, 0]
    assert mask[blocked] == 0
    assert mask.sum() == 4
    result = sim.step(np.array([[blocked]]))
    assert result.action_applied[0, 0] == 0
    assert result.reward_terms["lane_change"][0, 0] == 0.0
    st = sim.state
    assert st.lane[0, 0] == st.target_lane[0, 0] == lane
    assert st.y_m[0, 0] == lane_centre(lane)


def test_single_lane_road_masks_both_lateral_actions():
    sim = scripted_sim([], ego_lane=0, overrides={"road.lane_count": 1})
    assert sim.action_mask()[0, 0].tolist() == [1, 1, 1, 0, 0]


def test_cruise_actions_step_the_target_by_5_kmh_within_40_to_80():
    # The remembered-target variant: the actions move a target kept between decisions.
    sim = scripted_sim(
        [],
        ego_lane=2,
        ego_speed_kmh=60.0,
        overrides={"ego.cruise_mode": "remembered", "ego_vector.fields": ["cruise_target_mps"]},
    )
    st = sim.state
    targets = []
    for action in [1] * 6 + [2] * 12 + [1]:
        result = sim.step(np.array([[action]]))
        assert result.action_applied[0, 0] == action
        targets.append(round(st.desired_speed_mps[0, 0] / KMH, 6))
    assert targets == [65, 70, 75, 80, 80, 80, 75, 70, 65, 60, 55, 50, 45, 40, 40, 40, 40, 40, 45]
    assert sim.observe()["ego"][0, 0, 0] == pytest.approx(45 * KMH)
    # Keep leaves it alone; the lateral actions too.
    for action in (0, 3):
        sim.step(np.array([[action]]))
        assert st.desired_speed_mps[0, 0] == pytest.approx(45 * KMH)


def test_speed_follows_the_cruise_target():
    sim = scripted_sim(
        [], ego_lane=2, ego_speed_kmh=60.0, overrides={"ego.cruise_mode": "remembered"}
    )
    for _ in range(4):
        sim.step(np.array([[1]]))
    speeds = []
    for _ in range(100):
        keep(sim)
        speeds.append(sim.state.speed_mps[0, 0] / KMH)
    assert np.all(np.diff(speeds) >= 0)
    assert speeds[-1] == pytest.approx(80.0, abs=0.5)
    assert max(speeds) <= 80.0 + 1e-9


@pytest.mark.parametrize("speed_kmh", [40.0, 60.0, 80.0])
def test_one_decision_is_0_4_seconds(speed_kmh):
    sim = scripted_sim([], ego_lane=2, ego_speed_kmh=speed_kmh)
    st = sim.state
    for k in range(1, 6):
        keep(sim)
        assert st.x_m[0, 0] == pytest.approx(k * speed_kmh * KMH * DECISION_S, rel=1e-9)
        assert st.speed_mps[0, 0] == pytest.approx(speed_kmh * KMH, rel=1e-9)
    assert st.frame[0] == 5 * 4
    assert sim.decision_period_s == pytest.approx(DECISION_S)


def test_frames_per_decision_and_dt_set_the_decision_period():
    sim = scripted_sim(
        [],
        ego_lane=2,
        ego_speed_kmh=72.0,
        overrides={"episode.frames_per_decision": 5, "episode.physics_dt_s": 0.05},
    )
    keep(sim)
    assert sim.decision_period_s == pytest.approx(0.25)
    assert sim.state.x_m[0, 0] == pytest.approx(20.0 * 0.25, rel=1e-9)


def test_traffic_keeps_its_speed_on_a_free_lane():
    sim = scripted_sim(
        [Car(30.0, 0, 70.0, kind=ROAD_MAX), Car(-30.0, 4, 50.0, kind=STEADY)],
        ego_lane=2,
        ego_speed_kmh=60.0,
    )
    st = sim.state
    x0 = st.x_m[0].copy()
    for _ in range(10):
        keep(sim)
    assert st.x_m[0, 1] - x0[1] == pytest.approx(70.0 * KMH * 4.0, rel=1e-6)
    assert st.x_m[0, 2] - x0[2] == pytest.approx(50.0 * KMH * 4.0, rel=1e-6)
    assert st.lane[0, 1:].tolist() == [0, 4]


def test_stepping_a_subset_of_arenas_leaves_the_others_alone():
    config = make_config(overrides={"traffic.density": "light"})
    sim = HighwaySim(config, num_arenas=3)
    sim.reset(seeds=[1, 2, 3])
    before = {name: getattr(sim.state, name).copy() for name in ("x_m", "y_m", "speed_mps")}
    result = sim.step(np.array([[1], [3]]), arenas=np.array([0, 2]))
    assert result.reward.shape == (2, 1)
    for name, value in before.items():
        now = getattr(sim.state, name)
        assert np.array_equal(now[1], value[1]), name
    assert not np.array_equal(sim.state.x_m[0], before["x_m"][0])
    assert sim.state.decisions.tolist() == [1, 0, 1]
    # ... and a subset step equals the same arena stepped on its own.
    alone = HighwaySim(config, num_arenas=1)
    alone.reset(seeds=[3])
    alone.step(np.array([[3]]))
    assert np.array_equal(alone.state.x_m[0], sim.state.x_m[2])
    assert np.array_equal(alone.state.y_m[0], sim.state.y_m[2])


def test_step_refuses_bad_actions_and_unreset_arenas():
    sim = HighwaySim(make_config(), num_arenas=2)
    with pytest.raises(RuntimeError, match="reset"):
        sim.step(np.zeros((2, 1), dtype=np.int64))
    sim.reset(seeds=[0, 1])
    with pytest.raises(ValueError, match=r"shape \(2, 1\)"):
        sim.step(np.zeros((1, 1), dtype=np.int64))
    with pytest.raises(ValueError, match="integer"):
        sim.step(np.zeros((2, 1)))
    with pytest.raises(ValueError, match=r"\[0, 5\).*\[5\]"):
        sim.step(np.array([[0], [5]]))
    with pytest.raises(ValueError, match="expected 2 seeds"):
        sim.reset(seeds=[0])
    with pytest.raises(ValueError, match="num_arenas"):
        HighwaySim(make_config(), num_arenas=0)
