"""Rewards (Min et al. 2018, Table I) and the episode counters (Ho 2018)."""

from __future__ import annotations

import numpy as np
import pytest

from overtake.server.engine.env import HighwayEnv
from overtake.server.sim.units import KMH

from tests.support.scenes import Car, keep, scripted_sim

# Min et al.'s terms, as the preset lists them; the tests of Ho's "passed" term add it.
PAPER_TERMS = ("speed", "collision", "lane_change", "overtake", "warning")


def terms_of(result) -> dict[str, float]:
    return {name: float(value[0, 0]) for name, value in result.reward_terms.items()}


def assert_reward_is_the_sum_of_its_terms(result) -> None:
    total = sum(float(value[0, 0]) for value in result.reward_terms.values())
    assert float(result.reward[0, 0]) == pytest.approx(total, abs=1e-12)


# --- speed -----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "speed_kmh, expected", [(40.0, 0.0), (50.0, 0.25), (60.0, 0.5), (70.0, 0.75), (80.0, 1.0)]
)
def test_speed_term_is_linear_from_40_to_80_kmh(speed_kmh, expected):
    sim = scripted_sim([], ego_speed_kmh=speed_kmh)
    result = keep(sim)
    assert terms_of(result)["speed"] == pytest.approx(expected, abs=1e-9)
    assert float(result.reward[0, 0]) == pytest.approx(expected, abs=1e-9)
    assert_reward_is_the_sum_of_its_terms(result)


@pytest.mark.parametrize("speed_kmh, cruise_kmh", [(100.0, 80.0), (25.0, 40.0), (55.0, 80.0)])
@pytest.mark.parametrize("clip", [True, False])
def test_speed_term_uses_the_speed_after_the_decision_and_is_clipped(speed_kmh, cruise_kmh, clip):
    sim = scripted_sim(
        [],
        ego_speed_kmh=speed_kmh,
        cruise_kmh=cruise_kmh,
        # A kept cruise target the car speeds up or slows down to within the decision.
        overrides={"reward.clip_speed_term": clip, "ego.cruise_mode": "remembered"},
    )
    result = keep(sim)
    after_kmh = float(sim.state.speed_mps[0, 0]) / KMH
    assert after_kmh != pytest.approx(speed_kmh, abs=0.1)  # it did change within the decision
    raw = (after_kmh - 40.0) / 40.0
    expected = float(np.clip(raw, 0.0, 1.0)) if clip else raw
    assert terms_of(result)["speed"] == pytest.approx(expected, abs=1e-9)


def test_speed_term_follows_its_config():
    sim = scripted_sim(
        [],
        ego_speed_kmh=60.0,
        overrides={
            "reward.speed_min_kmh": 50.0,
            "reward.speed_max_kmh": 70.0,
            "reward.speed_reward_max": 2.0,
        },
    )
    assert terms_of(keep(sim))["speed"] == pytest.approx(1.0)


# --- collision -------------------------------------------------------------------------------


def test_changing_lane_into_a_car_alongside_is_a_collision():
    # The car alongside is a little faster, so braking (it sees the ego cut in) cannot save it.
    # Driver assistance would refuse this change; without it the change starts.
    sim = scripted_sim([Car(0.0, 3, 70.0)], ego_lane=2, overrides={"ego.lane_change_check": False})
    first = sim.step(np.array([[3]]))
    assert terms_of(first)["lane_change"] == -0.25
    assert not first.terminated[0, 0]
    for decision in range(2, 6):  # noqa: B007 (the decision of the collision, read below)
        result = keep(sim)
        if result.terminated[0, 0]:
            break
    else:
        pytest.fail("no collision while changing lane into a car alongside")
    # Boxes overlap once the lateral distance is below a car's width (1.8 m of 3.5 m).
    assert decision <= 4
    assert terms_of(result)["collision"] == -10.0
    assert float(result.reward[0, 0]) == pytest.approx(-10.0 + terms_of(result)["speed"])
    assert not result.truncated[0, 0]
    assert sim.metrics()["collisions"][0, 0] == 1
    assert_reward_is_the_sum_of_its_terms(result)


def test_overlapping_placement_collides_at_once():
    sim = scripted_sim([Car(3.0, 2, 60.0)], ego_lane=2)
    result = keep(sim)
    assert result.terminated[0, 0]
    assert terms_of(result)["collision"] == -10.0


def test_cars_in_neighbouring_lanes_do_not_collide():
    sim = scripted_sim([Car(0.0, 3, 60.0), Car(0.0, 1, 60.0)], ego_lane=2)
    for _ in range(20):
        result = keep(sim)
        assert not result.terminated[0, 0]
        assert terms_of(result)["collision"] == 0.0


def test_collision_reward_follows_its_config():
    sim = scripted_sim([Car(3.0, 2, 60.0)], ego_lane=2, overrides={"reward.collision": -3.0})
    assert terms_of(keep(sim))["collision"] == -3.0


# --- lane change -----------------------------------------------------------------------------


def test_lane_change_costs_0_25_on_the_decision_it_starts():
    sim = scripted_sim([], ego_lane=2, ego_speed_kmh=60.0)
    result = sim.step(np.array([[4]]))
    assert terms_of(result)["lane_change"] == -0.25
    assert float(result.reward[0, 0]) == pytest.approx(0.5 - 0.25)
    for _ in range(6):
        result = keep(sim)
        assert terms_of(result)["lane_change"] == 0.0
    result = sim.step(np.array([[3]]))
    assert terms_of(result)["lane_change"] == -0.25
    assert sim.metrics()["lane_changes"][0, 0] == 2


# --- overtakes -------------------------------------------------------------------------------


def drive_past_and_back(undo: bool, passed_reward: float = 0.0):
    """The ego (80 km/h, lane 2) passes a 40 km/h car in lane 3; the car speeds up and passes
    it back; then slows down and is passed again. Returns per-decision overtake and passed
    terms, the running overtake count and the car's position relative to the ego."""
    sim = scripted_sim(
        [Car(10.0, 3, 40.0)],
        ego_lane=2,
        ego_speed_kmh=80.0,
        cruise_kmh=80.0,
        overrides={
            "reward.undo_overtake_when_passed_back": undo,
            "reward.passed": passed_reward,
            "reward.terms": [*PAPER_TERMS, "passed"],
        },
    )
    st = sim.state
    overtake, passed, count, ahead = [], [], [], []
    for k in range(30):
        if k == 8:  # the car speeds up and passes the ego back ...
            st.speed_mps[0, 1] = st.desired_speed_mps[0, 1] = 110.0 * KMH
        if k == 20:  # ... and slows down again, so that the ego passes it once more
            st.speed_mps[0, 1] = st.desired_speed_mps[0, 1] = 40.0 * KMH
        result = keep(sim)
        assert not result.terminated[0, 0]
        assert_reward_is_the_sum_of_its_terms(result)
        overtake.append(terms_of(result)["overtake"])
        passed.append(terms_of(result)["passed"])
        count.append(int(sim.metrics()["overtakes"][0, 0]))
        ahead.append(float(st.x_m[0, 1] - st.x_m[0, 0]))
    return overtake, passed, count, ahead


def crossings(ahead: list[float]) -> tuple[list[int], list[int]]:
    """Decisions at which the car went from ahead to behind the ego, and back."""
    before = [10.0] + ahead[:-1]
    overtaken = [k for k in range(len(ahead)) if before[k] > 0 >= ahead[k]]
    passed_back = [k for k in range(len(ahead)) if before[k] <= 0 < ahead[k]]
    return overtaken, passed_back


def test_overtake_counts_once_per_car():
    overtake, passed, count, ahead = drive_past_and_back(undo=False)
    overtaken, passed_back = crossings(ahead)
    assert len(overtaken) == 2 and len(passed_back) == 1  # the scene did what it should
    first, again = overtaken
    assert overtake[first] == 0.5
    assert sum(overtake) == 0.5  # the re-pass earns nothing
    assert overtake[again] == 0.0
    assert count[first - 1] == 0 and count[first:] == [1] * (len(count) - first)
    assert passed == [0.0] * len(passed)  # Min et al.: no penalty for being passed


def test_overtake_is_undone_when_passed_back_if_configured():
    overtake, _, count, ahead = drive_past_and_back(undo=True)
    (first, again), (back,) = crossings(ahead)
    assert overtake[first] == 0.5
    assert overtake[back] == -0.5
    assert overtake[again] == 0.5
    assert sum(overtake) == 0.5
    assert count[first] == 1 and count[back] == 0 and count[-1] == 1


def test_being_passed_costs_the_passed_reward():
    _, passed, _, ahead = drive_past_and_back(undo=False, passed_reward=-1.0)
    _, (back,) = crossings(ahead)
    assert passed[back] == -1.0
    assert sum(passed) == -1.0


def test_car_overtaken_in_the_same_lane_by_changing_lanes_counts():
    # A slow car ahead in the ego's lane: move left, drive past it (back at its kept 80 km/h).
    sim = scripted_sim(
        [Car(30.0, 2, 40.0)],
        ego_lane=2,
        ego_speed_kmh=80.0,
        cruise_kmh=80.0,
        overrides={"ego.cruise_mode": "remembered"},
    )
    total = 0.0
    sim.step(np.array([[3]]))
    for _ in range(20):
        result = keep(sim)
        assert not result.terminated[0, 0]
        total += terms_of(result)["overtake"]
    assert sim.state.x_m[0, 1] < sim.state.x_m[0, 0]
    assert total == 0.5
    assert sim.metrics()["overtakes"][0, 0] == 1


def test_recycled_cars_are_not_counted_as_passes():
    # A car far behind falls out of range and is respawned elsewhere: neither an overtake
    # nor a pass, whatever side it reappears on.
    sim = scripted_sim(
        [Car(-145.0, 0, 40.0)],
        ego_lane=2,
        ego_speed_kmh=80.0,
        cruise_kmh=80.0,
        overrides={"reward.passed": -1.0, "reward.terms": [*PAPER_TERMS, "passed"]},
    )
    st = sim.state
    recycled = False
    for _ in range(10):
        before = float(st.x_m[0, 1])
        result = keep(sim)
        recycled |= abs(float(st.x_m[0, 1]) - before) > 20.0 or not st.active[0, 1]
        assert terms_of(result)["overtake"] == 0.0
        assert terms_of(result)["passed"] == 0.0
    assert recycled


# --- emergency brakes ------------------------------------------------------------------------


def braking_behind(leader_kmh: float, decisions: int, overrides=None):
    """The ego at 80 km/h (its kept cruise target) closes on a car 30 m ahead in its lane;
    returns the simulation and, per decision, the speed difference at its start (km/h) and
    how fast its speed fell over the decision (m/s^2)."""
    sim = scripted_sim(
        [Car(30.0, 2, leader_kmh)],
        ego_lane=2,
        ego_speed_kmh=80.0,
        cruise_kmh=80.0,
        overrides={"ego.cruise_mode": "remembered", **(overrides or {})},
    )
    st = sim.state
    differences, hardest = [], []
    for _ in range(decisions):
        differences.append(float(st.speed_mps[0, 0] - st.speed_mps[0, 1]) / KMH)
        before = float(st.speed_mps[0, 0])
        result = keep(sim)
        assert not result.terminated[0, 0]
        hardest.append((float(st.speed_mps[0, 0]) - before) / 0.4)
    return sim, np.array(differences), np.array(hardest)


def test_braking_for_a_much_slower_car_counts_an_emergency_brake_per_decision():
    sim, differences, slowing = braking_behind(40.0, 50)
    brakes = int(sim.metrics()["emergency_brakes"][0, 0])
    assert slowing.min() <= -4.0
    assert sim.state.speed_mps[0, 0] == pytest.approx(40.0 * KMH, rel=1e-3)
    # Several decisions of braking with a difference of at least 20 km/h (Ho: 40 km/h here);
    # none counts once the difference is below 20 km/h.
    assert 1 < brakes <= int(np.sum((differences >= 20.0) & (slowing < 0.0)))


@pytest.mark.parametrize("leader_kmh", [61.0, 65.0])
def test_braking_with_less_than_20_kmh_difference_is_not_an_emergency_brake(leader_kmh):
    sim, _, slowing = braking_behind(leader_kmh, 50)
    if leader_kmh == 61.0:
        assert slowing.min() <= -1.0  # firm braking, but only 19 km/h faster than the car ahead
    assert sim.metrics()["emergency_brakes"][0, 0] == 0


def test_emergency_brake_thresholds_follow_the_config():
    sim, *_ = braking_behind(61.0, 50, {"ego.emergency_speed_diff_kmh": 15.0})
    assert sim.metrics()["emergency_brakes"][0, 0] >= 1
    strict, *_ = braking_behind(40.0, 50, {"ego.emergency_decel_mps2": 15.0})
    assert strict.metrics()["emergency_brakes"][0, 0] == 0


def test_a_second_slow_car_adds_emergency_brakes():
    sim, *_ = braking_behind(40.0, 40)
    first = int(sim.metrics()["emergency_brakes"][0, 0])
    assert first >= 1
    # Another slow car appears ahead once the ego has been brought back to 80 km/h.
    st = sim.state
    st.x_m[0, 1] = st.x_m[0, 0] + 30.0
    st.speed_mps[0, 0] = 80.0 * KMH
    for _ in range(40):
        keep(sim)
    assert sim.metrics()["emergency_brakes"][0, 0] > first


# --- episode metrics -------------------------------------------------------------------------


def test_episode_metrics_at_the_end_of_an_episode():
    env = HighwayEnv(
        overrides={
            "traffic.vehicle_count": 0,
            "episode.max_decisions": 20,
            "ego.cruise_mode": "remembered",
        }
    )
    env.reset(seed=3)
    x0 = float(env.sim.state.x_m[0, 0])
    left_ok = bool(env.action_masks()[3])
    there, back = (3, 4) if left_ok else (4, 3)
    actions = [1, 1, 1, there, 0, 0, 0, 0, 0, 2, 2, 2, 2, 2, 2, 2, back, 0, 0, 0]
    total = 0.0
    for k, action in enumerate(actions):
        _, reward, terminated, truncated, info = env.step(action)
        total += reward
        assert not terminated
        assert truncated == (k == len(actions) - 1)
        assert ("metrics" in info) == truncated
    metrics = info["metrics"]
    distance = float(env.sim.state.x_m[0, 0]) - x0
    elapsed_s = 20 * 0.4
    assert metrics["distance_m"] == pytest.approx(distance)
    assert metrics["avg_speed_kmh"] == pytest.approx(distance / elapsed_s * 3.6)
    assert 55.0 < metrics["avg_speed_kmh"] < 80.0
    assert metrics["lane_changes"] == 2
    assert metrics["collisions"] == 0 and metrics["overtakes"] == 0
    assert metrics["emergency_brakes"] == 0
    assert metrics["decisions"] == 20
    assert metrics["return"] == pytest.approx(total)
    assert set(metrics) == {
        "avg_speed_kmh",
        "lane_changes",
        "overtakes",
        "collisions",
        "emergency_brakes",
        "distance_m",
        "return",
        "decisions",
        "traffic_cars",
    }
    assert metrics["traffic_cars"] == 0.0


def test_metrics_restart_with_each_episode():
    env = HighwayEnv(overrides={"traffic.vehicle_count": 0, "episode.max_decisions": 5})
    env.reset(seed=1)
    for _ in range(5):
        *_, info = env.step(3 if env.action_masks()[3] else 4)
    first = info["metrics"]
    assert first["lane_changes"] == 1 and first["decisions"] == 5
    env.reset()
    for _ in range(5):
        *_, info = env.step(0)
    assert info["metrics"]["lane_changes"] == 0
    assert info["metrics"]["decisions"] == 5
    assert info["metrics"]["avg_speed_kmh"] == pytest.approx(60.0)
