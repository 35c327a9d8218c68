"""Ho's set-up (2018) as the ``ho2018`` preset: the occupancy grid and the action stack, speed
steps with the Table 3 rules and his safety rule, every pass rewarded, the alternation penalty,
emergency brakes as §6.2 defines them, and 20 / 40 / 60 cars on a 7-lane road."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import overtake.client  # noqa: F401  (registers the environments)
from overtake.client.commands import UsageError
from overtake.client.drivers import GridRuleDriver
from overtake.client.episodes import baseline_policy, make_vector_env, run_episodes
from overtake.protocol import HIGHWAY_ENV_ID
from overtake.protocol.vocabulary import CRUISE_DOWN, CRUISE_UP, KEEP, LANE_LEFT, LANE_RIGHT
from overtake.server.sim import HighwaySim, make_config
from overtake.server.sim.units import KMH

from conftest import Car, keep, scripted_sim

OWN_LANE = 3  # the middle of seven
LEFT_COLUMN, OWN_COLUMN, RIGHT_COLUMN = range(3)


def ho_sim(cars=(), *, ego_lane=OWN_LANE, ego_speed_kmh=60.0, **overrides) -> HighwaySim:
    return scripted_sim(
        list(cars),
        ego_lane=ego_lane,
        ego_speed_kmh=ego_speed_kmh,
        preset="ho2018",
        overrides=overrides,
    )


def grid_of(sim: HighwaySim) -> np.ndarray:
    return sim.observe()["grid"][0, 0]


def speed_kmh(sim: HighwaySim) -> float:
    return float(sim.state.speed_mps[0, 0]) / KMH


def rows_with(column: np.ndarray) -> list[int]:
    return np.flatnonzero(column == 1).tolist()


# --- the observation (§5, §6.1) -----------------------------------------------------------------


def test_the_preset_observes_the_grid_and_the_action_stack():
    env = gym.make(HIGHWAY_ENV_ID, preset="ho2018")
    space = env.observation_space
    assert sorted(space.spaces) == ["actions", "grid"]  # no LIDAR, camera or ego vector
    assert space["grid"].shape == (36, 3) and space["grid"].dtype == np.int8
    assert space["actions"].shape == (4,)
    obs, _ = env.reset(seed=3)
    assert space.contains(obs)
    env.close()


def test_a_car_covers_the_cells_of_its_body_in_its_lane_and_only_those():
    # 36 cells of 1 m (his boxes) from 24.5 m ahead of the agent's centre (row 0: 21 ahead of
    # its front bumper) to 11.5 m behind. A 7 m car centred 10 m ahead spans 6.5-13.5 m: rows
    # 11-17; one centred 8 m behind spans -11.5 to -4.5 m: rows 29-35. The car 30 m ahead
    # (from 26.5 m) is out of sight, and the agent is no obstacle to itself.
    sim = ho_sim(
        [
            Car(dx=10.0, lane=OWN_LANE + 1, speed_kmh=60.0),
            Car(dx=-8.0, lane=OWN_LANE - 1, speed_kmh=60.0),
            Car(dx=30.0, lane=OWN_LANE, speed_kmh=60.0),
        ]
    )
    grid = grid_of(sim)
    assert rows_with(grid[:, LEFT_COLUMN]) == list(range(11, 18))
    assert rows_with(grid[:, RIGHT_COLUMN]) == list(range(29, 36))
    assert rows_with(grid[:, OWN_COLUMN]) == []
    assert set(np.unique(grid).tolist()) == {0, 1}


def test_a_car_changing_lanes_occupies_both():
    sim = ho_sim([Car(dx=5.0, lane=OWN_LANE + 1, speed_kmh=60.0)])
    sim.state.target_lane[0, 1] = OWN_LANE
    grid = grid_of(sim)
    assert rows_with(grid[:, LEFT_COLUMN]) == rows_with(grid[:, OWN_COLUMN]) != []


def test_lanes_beyond_the_road_read_minus_one_or_the_value_chosen():
    rightmost = grid_of(ho_sim(ego_lane=0))
    assert (rightmost[:, RIGHT_COLUMN] == -1).all() and (rightmost[:, :2] == 0).all()
    leftmost = grid_of(ho_sim(ego_lane=6))
    assert (leftmost[:, LEFT_COLUMN] == -1).all()
    boolean = grid_of(ho_sim(ego_lane=0, **{"grid.off_road_value": 0}))
    assert (boolean == 0).all()


def test_the_action_stack_holds_the_last_four_actions_applied():
    # A car beside on the right: the right change is refused and stacks as keep.
    sim = ho_sim([Car(dx=0.0, lane=OWN_LANE - 1, speed_kmh=60.0)])
    assert sim.observe()["actions"][0, 0].tolist() == [KEEP] * 4
    for action in (CRUISE_UP, LANE_RIGHT, CRUISE_DOWN):
        sim.step(np.array([[action]]))
    assert sim.observe()["actions"][0, 0].tolist() == [KEEP, CRUISE_UP, KEEP, CRUISE_DOWN]
    sim.step(np.array([[LANE_LEFT]]))
    assert sim.observe()["actions"][0, 0].tolist() == [CRUISE_UP, KEEP, CRUISE_DOWN, LANE_LEFT]


# --- speed steps (§4, Table 3) and the safety rule ----------------------------------------------


@pytest.mark.parametrize(
    "rule,action,change_kmh",
    [
        # Table 3: the decision's frame, then 3 skipped frames of 1 km/h each.
        ("table3", CRUISE_UP, 4.0),  # A, then A A A
        ("table3", CRUISE_DOWN, 2.0),  # D, then A A A
        ("table3", KEEP, 0.0),
        ("table3", LANE_LEFT, 0.0),  # L, then M M M
        ("repeat", CRUISE_UP, 4.0),  # his code: the decision's move again
        ("repeat", CRUISE_DOWN, -4.0),
    ],
)
def test_a_decision_steps_the_speed_frame_by_frame(rule, action, change_kmh):
    sim = ho_sim(**{"ego.skipped_frames": rule})
    sim.step(np.array([[action]]))
    assert speed_kmh(sim) == pytest.approx(60.0 + change_kmh)


def test_the_speed_stays_within_0_and_110_kmh():
    fast = ho_sim(ego_speed_kmh=108.0)
    fast.step(np.array([[CRUISE_UP]]))
    assert speed_kmh(fast) == pytest.approx(110.0)
    slow = ho_sim(ego_speed_kmh=1.0, **{"ego.skipped_frames": "repeat"})
    slow.step(np.array([[CRUISE_DOWN]]))
    assert speed_kmh(slow) == 0.0


def test_a_slower_car_within_the_safety_gap_is_matched_at_once_and_counted_as_an_emergency_brake():
    # 2.5 m bumper to bumper (7 m cars, centres 9.5 m apart), 30 km/h slower: an emergency
    # brake.
    sim = ho_sim([Car(dx=9.5, lane=OWN_LANE, speed_kmh=60.0)], ego_speed_kmh=90.0)
    sim.step(np.array([[CRUISE_UP]]))
    assert speed_kmh(sim) == pytest.approx(60.0, abs=0.01)
    assert sim.metrics()["emergency_brakes"][0, 0] == 1
    # 10 km/h slower: matched too, but no emergency brake (§6.2: at least 20 km/h).
    mild = ho_sim([Car(dx=9.5, lane=OWN_LANE, speed_kmh=60.0)], ego_speed_kmh=70.0)
    keep(mild)
    assert speed_kmh(mild) == pytest.approx(60.0, abs=0.01)
    assert mild.metrics()["emergency_brakes"][0, 0] == 0


def test_no_accelerating_with_a_car_within_the_safety_gap_even_a_faster_one():
    sim = ho_sim([Car(dx=9.5, lane=OWN_LANE, speed_kmh=80.0)], ego_speed_kmh=60.0)
    sim.step(np.array([[CRUISE_UP]]))
    assert speed_kmh(sim) == pytest.approx(60.0)
    # Once it is beyond the gap (10 m bumper to bumper), the agent accelerates again.
    far = ho_sim([Car(dx=17.0, lane=OWN_LANE, speed_kmh=80.0)], ego_speed_kmh=60.0)
    far.step(np.array([[CRUISE_UP]]))
    assert speed_kmh(far) == pytest.approx(64.0)


def test_traffic_yields_to_the_agent_in_ho2018_and_not_in_min_et_al_s_rule():
    def rear_ended(yields: bool) -> bool:
        # A car 60 km/h faster 10 m behind the agent's rear bumper, on a road of one lane (it
        # cannot swerve), braking at most 6 m/s^2 by car-following (it needs 23 m): only the
        # safety rule's speed cap, Ho's "match the car ahead at once", saves it.
        sim = ho_sim(
            [Car(dx=-17.0, lane=0, speed_kmh=100.0)],
            ego_lane=0,
            ego_speed_kmh=40.0,
            **{
                "traffic.yield_to_agents": yields,
                "road.lane_count": 1,
                "traffic.max_decel_mps2": 6.0,
                "traffic.comfort_decel_mps2": 2.5,
            },
        )
        return any(keep(sim).terminated[0, 0] for _ in range(40))

    assert not rear_ended(True)
    assert rear_ended(False)


def test_only_an_unchecked_lane_change_can_collide():
    def change_into_a_car(check: bool):
        sim = ho_sim(
            [Car(dx=1.0, lane=OWN_LANE + 1, speed_kmh=60.0)], **{"ego.lane_change_check": check}
        )
        first = sim.step(np.array([[LANE_LEFT]]))
        crashed = first.terminated[0, 0] or any(keep(sim).terminated[0, 0] for _ in range(6))
        return int(first.action_applied[0, 0]), crashed

    assert change_into_a_car(True) == (KEEP, False)
    assert change_into_a_car(False) == (LANE_LEFT, True)


# --- the reward (§7.2, Table 6) -----------------------------------------------------------------


def test_every_crossing_counts_plus_or_minus_one():
    sim = ho_sim([Car(dx=6.0, lane=OWN_LANE + 1, speed_kmh=60.0)], ego_speed_kmh=100.0)
    st = sim.state

    def run(decisions: int) -> dict[str, float]:
        totals = {"overtake": 0.0, "passed": 0.0}
        for _ in range(decisions):
            terms = keep(sim).reward_terms
            for name in totals:
                totals[name] += float(terms[name][0, 0])
        return totals

    # Eight decisions of 0.32 s at 40 km/h between them move it 28 m: within the kept road
    # (50 m behind, 90 m ahead), so the same car is passed each time.
    assert run(8) == {"overtake": 1.0, "passed": 0.0}  # passes it
    st.speed_mps[0, 0] = 20.0 * KMH
    sim.state_written()
    assert run(8) == {"overtake": 0.0, "passed": -1.0}  # it passes back
    st.speed_mps[0, 0] = 110.0 * KMH
    sim.state_written()
    assert run(8) == {"overtake": 1.0, "passed": 0.0}  # the same car again: it counts again
    assert sim.metrics()["overtakes"][0, 0] == 2


def test_a_lane_change_opposite_to_a_recent_one_costs_the_alternation_penalty():
    sim = ho_sim()
    rewards = []
    # Left, then right once the change is over (0.24 s, within the decision of 0.32 s), while
    # the left is still among the last four actions; then right again, with no left among them.
    for action in (LANE_LEFT, KEEP, KEEP, KEEP, LANE_RIGHT, KEEP, KEEP, KEEP, KEEP, LANE_RIGHT):
        result = sim.step(np.array([[action]]))
        assert result.action_applied[0, 0] == action
        rewards.append(float(result.reward_terms["alternation"][0, 0]))
    assert rewards[4] == pytest.approx(-0.00001)
    assert rewards[:4] + rewards[5:] == [0.0] * 9


# --- the road (Table 4) -------------------------------------------------------------------------


@pytest.mark.parametrize("density,cars", [("light", 20), ("medium", 40), ("heavy", 60)])
def test_the_density_holds_its_cars_on_the_road(density, cars):
    sim = HighwaySim(make_config("ho2018", {"traffic.density": density}), num_arenas=4)
    sim.reset(seeds=[1, 2, 3, 4])
    rng = np.random.default_rng(0)
    for _ in range(250):
        sim.step(rng.integers(0, 5, size=(4, 1)))
    on_road = sim.metrics()["traffic_cars"].mean()
    assert on_road >= 0.9 * cars


def test_ho_s_traffic_does_not_collide_with_random_driving():
    sim = HighwaySim(make_config("ho2018", {"traffic.density": "heavy"}), num_arenas=4)
    sim.reset(seeds=[5, 6, 7, 8])
    rng = np.random.default_rng(1)
    kinds = set()
    for _ in range(300):
        assert not sim.step(rng.integers(0, 5, size=(4, 1))).terminated.any()
        kinds |= set(sim.state.kind[:, 1:][sim.state.active[:, 1:]].tolist())
    assert kinds == {0, 1, 2}  # steady, road maximum, lane switcher: all three on the road


# --- the reference policies on Ho's set-up ------------------------------------------------------


def blank_grid() -> np.ndarray:
    return np.zeros((1, 36, 3), dtype=np.int8)


ALL_ALLOWED = np.ones((1, 5), dtype=np.int8)


def test_the_grid_rule_driver_accelerates_on_a_free_road():
    assert GridRuleDriver().act(blank_grid(), ALL_ALLOWED).tolist() == [CRUISE_UP]


@pytest.mark.parametrize(
    "left,right,expected",
    [
        ("free", "free", LANE_LEFT),  # both better: left on a tie
        ("beside", "free", LANE_RIGHT),  # a car beside on the left
        ("free", "off", LANE_LEFT),
        ("off", "beside", CRUISE_UP),  # nowhere to go: the safety rule keeps it behind
        ("blocked", "blocked", CRUISE_UP),  # no lane better by 4 m
    ],
)
def test_the_grid_rule_driver_leaves_a_blocked_lane_for_a_freer_one(left, right, expected):
    grid = blank_grid()
    grid[0, 9:15, OWN_COLUMN] = 1  # a car 7.75-12.25 m ahead: 5.5 m of room
    for column, state in ((LEFT_COLUMN, left), (RIGHT_COLUMN, right)):
        if state == "beside":
            grid[0, 22:28, column] = 1
        elif state == "off":
            grid[0, :, column] = -1
        elif state == "blocked":
            grid[0, 8:14, column] = 1  # a car about as near as the own lane's
    assert GridRuleDriver().act(grid, ALL_ALLOWED).tolist() == [expected]


def test_the_grid_rule_driver_obeys_the_action_mask():
    grid = blank_grid()
    grid[0, 9:15, OWN_COLUMN] = 1
    mask = ALL_ALLOWED.copy()
    mask[0, LANE_LEFT] = 0
    assert GridRuleDriver().act(grid, mask).tolist() == [LANE_RIGHT]


def test_every_reference_policy_drives_ho2018_without_further_flags():
    short = {"episode.max_decisions": 60, "traffic.density": "medium"}
    speeds = {}
    for policy in ("idle", "random", "rule", "planner"):
        envs = make_vector_env("ho2018", short, 3, None)
        act = baseline_policy(policy, envs.unwrapped.behaviour_spec, 0, 3, envs)
        rows, decisions, _ = run_episodes(envs, act, 3, 100)
        envs.close()
        assert decisions == 3 * 60 and all(row["collisions"] == 0 for row in rows)
        speeds[policy] = np.mean([row["avg_speed_kmh"] for row in rows])
    # Idle holds its 60 km/h start (or less); the rule driver and the planner accelerate
    # towards 110 km/h; random driving, its decelerations repeated as its accelerations are,
    # goes nowhere fast.
    assert speeds["idle"] <= 60.0 + 1e-6
    assert min(speeds["rule"], speeds["planner"]) > speeds["idle"] + 5.0
    assert speeds["random"] < min(speeds["rule"], speeds["planner"]) - 20.0


def test_the_grid_rule_driver_needs_the_lanes_either_side():
    envs = make_vector_env("ho2018", {"grid.side_lanes": 2}, 1, None)
    with pytest.raises(UsageError, match="grid.side_lanes = 2"):
        baseline_policy("rule", envs.unwrapped.behaviour_spec, 0, 1, envs)
    envs.close()


def test_evaluation_decides_every_frame_as_his_code_does():
    """Ho's code skips frames only while training (gui.py): overtake-eval drives his 4,000
    frames with a decision at each, and --no-paper-evaluation as in training, 1,000 decisions
    of 4 frames; both the same 320 s of road."""
    from overtake.trainers.evaluate import EvalConfig
    from overtake.trainers.evaluate import main as evaluate

    every_frame = evaluate(EvalConfig(preset="ho2018", policy="idle", episodes=1))
    as_trained = evaluate(
        EvalConfig(preset="ho2018", policy="idle", episodes=1, paper_evaluation=False)
    )
    assert every_frame["overrides"]["episode.frames_per_decision"] == 1
    assert [row["decisions"] for row in every_frame["episodes"]] == [4000]
    assert [row["decisions"] for row in as_trained["episodes"]] == [1000]
    # Idle driving over the same road: the same distance either way.
    distance = [r["episodes"][0]["distance_m"] for r in (every_frame, as_trained)]
    assert distance[0] == pytest.approx(distance[1], rel=0.05)
