"""Min et al.'s spawners (``traffic.entry = "spawners"``, min2018's traffic since issue 68):
the sides and windows of the spawns, the timing of the tries, the 10 m clearance, the cars
that leave (beyond 100 m, or touching), the count as a most, and a reset's empty road."""

from __future__ import annotations

import numpy as np
import pytest

from overtake.server.sim import HighwaySim, make_config
from overtake.server.sim.spawners import attempt_interval_cdf, spawner_shares

from tests.support.scenes import Car, keep, scripted_sim

LANE_WIDTH = 3.5
CLEARANCE_ACROSS_M = 10.0 / 7.0 * LANE_WIDTH  # their margin of 10 over lanes 7 apart
# A road that never fills and nobody leaves: every try places its car (the draws alone).
OPEN_ROAD = {
    "camera.enabled": False,
    "lidar.enabled": False,
    "traffic.vehicle_count": 200,
    "traffic.keep_ahead_m": 5000.0,
    "traffic.keep_behind_m": 5000.0,
    "traffic.spawner_clearance_m": 0.0,
}


def _sim(overrides: dict, arenas: int, seed: int = 0) -> HighwaySim:
    sim = HighwaySim(make_config("min2018", overrides), num_arenas=arenas)
    sim.reset(seeds=list(range(seed, seed + arenas)))
    return sim


def _new_cars(before_active: np.ndarray, before_own: np.ndarray, sim: HighwaySim) -> np.ndarray:
    """(A, T) the traffic slots that got a new car in the last decision."""
    st = sim.state
    return st.active[:, 1:] & (~before_active | (st.own_speed_mps[:, 1:] != before_own))


def _spawns(sim: HighwaySim, decisions: int) -> list[tuple[int, int, float, float]]:
    """Every spawn of ``decisions`` decisions of keep: (arena, slot, metres ahead of the
    agent, metres across from it) at the moment it appeared."""
    st = sim.state
    found = []
    for _ in range(decisions):
        active, own = st.active[:, 1:].copy(), st.own_speed_mps[:, 1:].copy()
        keep(sim)
        for arena, t in zip(*np.nonzero(_new_cars(active, own, sim)), strict=True):
            dx = st.x_m[arena, 1 + t] - st.x_m[arena, 0]
            dy = st.y_m[arena, 1 + t] - st.y_m[arena, 0]
            found.append((int(arena), int(1 + t), float(dx), float(dy)))
    return found


def test_the_tries_come_every_2_12_s_on_average_not_every_2_to_8_s():
    """Their spawners redraw Random.Range(2, 8) (whole seconds 2-7) every fixed step of 0.02 s
    and try once their clock exceeds the draw: the clock first exceeds 2 s at the 101st step
    (a 32-bit float), and then each step tries with one chance in six."""
    config = make_config("min2018")
    cdf = attempt_interval_cdf(config.traffic)
    chances = np.diff(cdf, prepend=0.0)
    steps = np.arange(1, cdf.size + 1)
    assert chances[:100].sum() == 0.0 and chances[100] == pytest.approx(1 / 6)
    mean_s = float((steps * chances).sum()) * 0.02
    assert mean_s == pytest.approx(2.12, abs=0.005)
    assert cdf[149] == pytest.approx(1 - (5 / 6) ** 50)  # within 3 s, nearly always
    assert cdf[-1] == 1.0 and steps[-1] == 351  # past 7 s every wait is below the clock
    # On the road: with every try placing a car, each spawner places one per 2.12 s.
    arenas, decisions = 16, 100
    sim = _sim(OPEN_ROAD, arenas)
    spawns = len(_spawns(sim, decisions))
    seconds = decisions * 0.4
    per_spawner = spawns / arenas / 8
    # The first try of each comes at a uniform point of one wait: half a wait more.
    expected = seconds / mean_s + 0.5
    assert per_spawner == pytest.approx(expected, rel=0.05)


def test_a_spawn_is_ahead_seven_times_in_ten_in_their_windows_and_lanes():
    spawns = _spawns(_sim(OPEN_ROAD, 48), 100)
    dx = np.array([spawn[2] for spawn in spawns])
    assert dx.size > 4000
    ahead = dx > 0
    assert ahead.mean() == pytest.approx(0.70, abs=0.03)
    # Whole metres, 30-89 ahead and 30-59 behind (Unity's integer Random.Range), all of them.
    assert np.allclose(dx, np.round(dx), rtol=0.0, atol=1e-9)
    assert set(np.round(dx[ahead]).astype(int)) == set(range(30, 90))
    assert set(np.round(-dx[~ahead]).astype(int)) == set(range(30, 60))
    # Every lane evenly (Random.Range(1, 6)).
    sim = _sim({**OPEN_ROAD, "traffic.vehicle_count": 100}, 16)
    st = sim.state
    absolute = []
    for _ in range(60):
        active, own = st.active[:, 1:].copy(), st.own_speed_mps[:, 1:].copy()
        keep(sim)
        absolute += st.lane[:, 1:][_new_cars(active, own, sim)].tolist()
    lane_shares = np.bincount(absolute, minlength=5) / len(absolute)
    assert lane_shares == pytest.approx(np.full(5, 0.2), abs=0.03)


def test_no_spawn_lands_within_10_m_along_and_a_lane_across_of_another_car():
    """Their IsOtherVehicle: no car's centre within 10 along the road and 10 across (lanes 7
    apart there, 3.5 m here: 5 m). Without the margin, some spawns land inside it."""

    def crowded_spawns(clearance_m: float) -> tuple[int, int]:
        sim = _sim(
            {"camera.enabled": False, "traffic.density": "heavy",
             "traffic.spawner_clearance_m": clearance_m},
            16,
        )  # fmt: skip
        st = sim.state
        crowded = spawned = 0
        for _ in range(150):
            active, own = st.active[:, 1:].copy(), st.own_speed_mps[:, 1:].copy()
            keep(sim)
            for arena, t in zip(*np.nonzero(_new_cars(active, own, sim)), strict=True):
                others = st.active[arena].copy()
                others[1 + t] = False
                near = (np.abs(st.x_m[arena] - st.x_m[arena, 1 + t]) < 10.0) & (
                    np.abs(st.y_m[arena] - st.y_m[arena, 1 + t]) < CLEARANCE_ACROSS_M
                )
                crowded += int((near & others).any())
                spawned += 1
        return crowded, spawned

    crowded, spawned = crowded_spawns(10.0)
    assert spawned > 500 and crowded == 0
    crowded, _ = crowded_spawns(0.0)
    assert crowded > 10


def test_no_car_is_kept_beyond_100_m_and_the_count_is_a_most():
    arenas = 8
    for density, count in (("light", 10), ("medium", 20), ("heavy", 32)):
        sim = _sim({"camera.enabled": False, "traffic.density": density}, arenas)
        st = sim.state
        rng = np.random.default_rng(1)
        on_road = []
        for _ in range(400):
            result = sim.step(rng.integers(0, 5, (arenas, 1)))
            dx = st.x_m[:, 1:] - st.x_m[:, :1]
            dy = st.y_m[:, 1:] - st.y_m[:, :1]
            distance = np.hypot(dx, dy)[st.active[:, 1:]]
            assert distance.size == 0 or distance.max() <= 100.0
            cars = st.active[:, 1:].sum(axis=1)
            assert cars.max() <= count
            on_road.append(cars)
            # Each spawner keeps at most its share, in its own slots.
            shares = spawner_shares(count, 8)
            first = np.concatenate(([0], np.cumsum(shares)[:-1]))
            for s in range(8):
                block = st.active[:, 1 + first[s] : 1 + first[s] + shares[s]]
                assert block.sum(axis=1).max() <= shares[s]
            ended = np.flatnonzero(result.ended[:, 0])
            if ended.size:
                sim.reset(ended)
        on_road = np.array(on_road)
        # The population rises and falls: it is not held at the count.
        assert on_road.min() < on_road.max()
        assert on_road.mean() < count


def test_the_metrics_report_the_varying_population():
    sim = _sim({"camera.enabled": False, "traffic.density": "heavy"}, 2)
    st = sim.state
    counted = []
    for _ in range(100):
        keep(sim)
        counted.append(st.active[:, 1:].sum(axis=1))
    np.testing.assert_allclose(sim.metrics()["traffic_cars"][:, 0], np.mean(counted, axis=0))
    assert (sim.metrics()["traffic_cars"][:, 0] < 32).all()


def test_cars_that_touch_leave_the_road_both_of_them():
    # Cars 1 and 2 abreast, 1 m apart across (car 2 in lane 2 but drawn towards lane 1: its
    # lateral position written by hand, which nothing moves outside a lane change): their
    # boxes overlap and both leave. Car 3, abreast a lane over, keeps its distance and stays.
    sim = scripted_sim([Car(40.0, 1, 60.0), Car(40.0, 2, 60.0), Car(40.0, 3, 60.0)])
    st = sim.state
    st.y_m[0, 2] = st.y_m[0, 1] + 1.0
    keep(sim)
    assert st.active[0].tolist() == [True, False, False, True]
    # Side by side in adjacent lanes is not touching.
    sim = scripted_sim([Car(40.0, 1, 60.0), Car(40.0, 2, 60.0)])
    keep(sim)
    assert sim.state.active[0].all()


def test_a_car_leaves_beyond_100_m_in_a_straight_line_and_is_not_recycled():
    # Everyone at 60 km/h: nobody moves relative to the agent (lane 2). 99 m ahead two lanes
    # over is 99.2 m away in a straight line: kept; 99.9 m ahead two lanes over is 100.1 m:
    # gone (the treadmill, along the road, kept it). Behind as ahead.
    sim = scripted_sim(
        [Car(99.0, 4, 60.0), Car(99.9, 0, 60.0), Car(-99.5, 2, 60.0), Car(-100.5, 2, 60.0)]
    )
    keep(sim)
    st = sim.state
    assert st.active[0].tolist() == [True, True, False, True, False]
    # Nothing comes back (a scripted scene's spawners wait): the slots stay empty.
    for _ in range(5):
        keep(sim)
    assert st.active[0].tolist() == [True, True, False, True, False]


def test_a_reset_empties_the_road_and_the_spawners_fill_it_again():
    sim = _sim({"camera.enabled": False, "traffic.density": "heavy"}, 4)
    st = sim.state
    assert not st.active[:, 1:].any()  # the road starts empty
    for _ in range(50):
        keep(sim)
    assert st.active[:, 1:].sum(axis=1).min() >= 10
    sim.reset([1, 2])
    assert not st.active[[1, 2], 1:].any()
    assert st.active[[0, 3], 1:].any(axis=1).all()  # the others are left alone
    # Every spawner tries within one wait of a reset (at most 7.02 s; 2.12 s on average).
    assert (st.spawner_wait_s[[1, 2]] <= 7.02).all()
    for _ in range(6):  # 2.4 s
        keep(sim)
    assert st.active[[1, 2], 1:].sum(axis=1).min() >= 4


def test_each_spawner_keeps_an_equal_share_the_first_ones_one_more():
    assert spawner_shares(20, 8).tolist() == [3, 3, 3, 3, 2, 2, 2, 2]
    assert spawner_shares(10, 8).tolist() == [2, 2, 1, 1, 1, 1, 1, 1]
    assert spawner_shares(5, 8).tolist() == [1, 1, 1, 1, 1, 0, 0, 0]
    for count in range(65):
        assert spawner_shares(count, 8).sum() == count


def test_a_spawner_with_its_share_on_the_road_places_nothing():
    # One car a spawner (count 8): with every car on the road, no try places one.
    cars = [Car(35.0 + 12.0 * i, i % 5, 60.0) for i in range(8)]
    sim = scripted_sim(cars, overrides={"traffic.keep_ahead_m": 5000.0})
    st = sim.state
    st.spawner_wait_s[:] = 0.0  # scripted scenes hold their spawners: these try at once
    own = st.own_speed_mps[0].copy()
    for _ in range(30):  # 12 s: every spawner tries about five times
        keep(sim)
    assert st.active[0].all() and np.array_equal(st.own_speed_mps[0], own)
