"""Ho's set-up (2018) as the ``ho2018`` preset: the occupancy grid and the action stack, speed
steps with the Table 3 rules and his safety rule, every pass rewarded, the alternation penalty,
emergency brakes as §6.2 defines them, and 20 / 40 / 60 cars on a 7-lane road."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest

import overtake.client  # noqa: F401  (registers the environments)
from overtake.cli import UsageError
from overtake.client.episodes.runner import baseline_policy, run_episodes
from overtake.client.episodes.scenario import Scenario, Where
from overtake.client.policies.drivers import GridRuleDriver
from overtake.envs import HIGHWAY_ENV_ID
from overtake.protocol.vocabulary import CRUISE_DOWN, CRUISE_UP, KEEP, LANE_LEFT, LANE_RIGHT
from overtake.server.sim import HighwaySim, make_config
from overtake.server.sim.units import KMH

from tests.support.scenes import ROAD_MAX, STEADY, Car, keep, scripted_sim

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


@pytest.mark.parametrize(
    "covered_by, left_rows, right_rows",
    [
        # His code (get_vision): a car marks 7 cells, from the one holding its front bumper.
        ("near_edge", range(10, 17), range(28, 35)),
        # Every cell a body covers part of: 8 where it does not sit on the cells' edges.
        ("any_part", range(10, 18), range(28, 36)),
    ],
)
def test_a_car_covers_the_cells_of_its_body_in_its_lane_and_only_those(
    covered_by, left_rows, right_rows
):
    # 36 cells of 1 m (his boxes) from 24.5 m ahead of the agent's centre (row 0: 21 ahead of
    # its front bumper) to 11.5 m behind: row i from 23.5 - i to 24.5 - i m. A 7 m car centred
    # 10.3 m ahead spans 6.8-13.8 m: its front in row 10, its rear in row 17; one centred 7.7
    # m behind spans -11.2 to -4.2 m: its front in row 28, its rear in row 35. The car 30 m
    # ahead (from 26.5 m) is out of sight, and the agent is no obstacle to itself.
    sim = ho_sim(
        [
            Car(dx=10.3, lane=OWN_LANE + 1, speed_kmh=60.0),
            Car(dx=-7.7, lane=OWN_LANE - 1, speed_kmh=60.0),
            Car(dx=30.0, lane=OWN_LANE, speed_kmh=60.0),
        ],
        **{"grid.covered_by": covered_by},
    )
    grid = grid_of(sim)
    assert rows_with(grid[:, LEFT_COLUMN]) == list(left_rows)
    assert rows_with(grid[:, RIGHT_COLUMN]) == list(right_rows)
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


# The action chosen repeated over the skipped frames, where a test is of the safety rule alone
# (with the preset's ego.applied_as_driven a braked decision goes on braking: tests below).
AS_CHOSEN = {"ego.applied_as_driven": False}


def test_a_slower_car_within_the_safety_gap_is_matched_at_once_and_counted_as_an_emergency_brake():
    # 2.5 m bumper to bumper (7 m cars, centres 9.5 m apart), 30 km/h slower: an emergency
    # brake.
    sim = ho_sim([Car(dx=9.5, lane=OWN_LANE, speed_kmh=60.0)], ego_speed_kmh=90.0, **AS_CHOSEN)
    sim.step(np.array([[CRUISE_UP]]))
    assert speed_kmh(sim) == pytest.approx(60.0, abs=0.01)
    assert sim.metrics()["emergency_brakes"][0, 0] == 1
    # 10 km/h slower: matched too, but no emergency brake (§6.2: at least 20 km/h).
    mild = ho_sim([Car(dx=9.5, lane=OWN_LANE, speed_kmh=60.0)], ego_speed_kmh=70.0, **AS_CHOSEN)
    keep(mild)
    assert speed_kmh(mild) == pytest.approx(60.0, abs=0.01)
    assert mild.metrics()["emergency_brakes"][0, 0] == 0


def test_emergency_brakes_are_counted_as_his_code_counts_them_the_brakes_his_rule_forces():
    """car.py's hard_brake_count: the safety rule takes the speed of a car in the front window
    more than 20 km/h slower (strictly); a deliberate brake towards a slow car farther ahead
    is not one (the count before issue 56 counted it: ``ego.emergency_brake_count``)."""
    exactly_20 = ho_sim(
        [Car(dx=9.5, lane=OWN_LANE, speed_kmh=60.0)], ego_speed_kmh=80.0, **AS_CHOSEN
    )
    keep(exactly_20)
    assert speed_kmh(exactly_20) == pytest.approx(60.0, abs=0.01)
    assert exactly_20.metrics()["emergency_brakes"][0, 0] == 0
    # A slow car 30 m ahead, braked for at 3.5 m/s^2 for a whole decision: no forced brake.
    far = ho_sim(
        [Car(dx=37.0, lane=OWN_LANE, speed_kmh=30.0)],
        ego_speed_kmh=90.0,
        **{"ego.skipped_frames": "repeat"},
    )
    far.step(np.array([[CRUISE_DOWN]]))
    assert speed_kmh(far) == pytest.approx(86.0)
    assert far.metrics()["emergency_brakes"][0, 0] == 0
    deliberate = ho_sim(
        [Car(dx=37.0, lane=OWN_LANE, speed_kmh=30.0)],
        ego_speed_kmh=90.0,
        **{"ego.skipped_frames": "repeat", "ego.emergency_brake_count": "deliberate"},
    )
    deliberate.step(np.array([[CRUISE_DOWN]]))
    assert deliberate.metrics()["emergency_brakes"][0, 0] == 1
    # Counted per frame the rule forces, as his code checks every frame: the car ahead
    # slowing again past the margin is a second one.
    twice = ho_sim([Car(dx=9.5, lane=OWN_LANE, speed_kmh=60.0)], ego_speed_kmh=90.0, **AS_CHOSEN)
    keep(twice)
    twice.state.speed_mps[0, 1] = 35.0 * KMH
    keep(twice)
    assert twice.metrics()["emergency_brakes"][0, 0] == 2
    with pytest.raises(ValueError, match="ego.emergency_brake_count"):
        make_config("min2018", {"ego.emergency_brake_count": "forced"})


def test_no_accelerating_with_a_car_within_the_safety_gap_even_a_faster_one():
    # 1.5 m bumper to bumper: the car 20 km/h faster opens the gap by 0.44 m a frame, still
    # within his 4 m after the decision's four frames.
    sim = ho_sim([Car(dx=8.5, lane=OWN_LANE, speed_kmh=80.0)], ego_speed_kmh=60.0)
    sim.step(np.array([[CRUISE_UP]]))
    assert speed_kmh(sim) == pytest.approx(60.0)
    # Once it is beyond the gap (10 m bumper to bumper), the agent accelerates again.
    far = ho_sim([Car(dx=17.0, lane=OWN_LANE, speed_kmh=80.0)], ego_speed_kmh=60.0)
    far.step(np.array([[CRUISE_UP]]))
    assert speed_kmh(far) == pytest.approx(64.0)


# --- the action applied as his car drove it (players/deep_traffic_player.py) ----------------------


def step_applied(sim: HighwaySim, action: int) -> int:
    return int(sim.step(np.array([[action]])).action_applied[0, 0])


@pytest.mark.parametrize("action", [KEEP, CRUISE_UP, CRUISE_DOWN, LANE_LEFT, LANE_RIGHT])
def test_on_a_free_road_the_action_applied_is_the_one_chosen(action):
    sim = ho_sim()
    assert step_applied(sim, action) == action
    assert sim.observe()["actions"][0, 0].tolist() == [KEEP, KEEP, KEEP, action]


@pytest.mark.parametrize("as_driven", [True, False])
def test_accelerate_behind_a_car_within_the_gap_is_keep_and_its_skipped_frames_keep(as_driven):
    # 3.5 m bumper to bumper, the car ahead 50 km/h faster: out of the 4 m gap after the
    # decision's first frame. His car.move makes the accelerate keep (a car in front: no "A"
    # among the moves), and the skipped frames repeat keep (action_cache); as chosen, they
    # accelerate once the gap has opened.
    sim = ho_sim(
        [Car(dx=10.5, lane=OWN_LANE, speed_kmh=110.0)],
        ego_speed_kmh=60.0,
        **{"ego.applied_as_driven": as_driven},
    )
    assert step_applied(sim, CRUISE_UP) == (KEEP if as_driven else CRUISE_UP)
    assert speed_kmh(sim) == pytest.approx(60.0 if as_driven else 63.0)
    assert sim.observe()["actions"][0, 0, -1] == (KEEP if as_driven else CRUISE_UP)


@pytest.mark.parametrize("action", [CRUISE_UP, KEEP, CRUISE_DOWN])
@pytest.mark.parametrize("as_driven", [True, False])
def test_behind_a_slower_car_within_the_gap_the_action_is_decelerate_and_goes_on_braking(
    action, as_driven
):
    # 2.5 m bumper to bumper, 30 km/h slower: the rule takes its 60 km/h at once (his "M" and
    # "A" are not among the moves, so car.move makes them "D"); the skipped frames repeat
    # decelerate, 1 km/h a frame (the car ahead no longer slower: his decelerate steps down).
    sim = ho_sim(
        [Car(dx=9.5, lane=OWN_LANE, speed_kmh=60.0)],
        ego_speed_kmh=90.0,
        **{"ego.applied_as_driven": as_driven},
    )
    applied = step_applied(sim, action)
    braking = as_driven or action == CRUISE_DOWN
    assert applied == (CRUISE_DOWN if as_driven else action)
    assert speed_kmh(sim) == pytest.approx(57.0 if braking else 60.0, abs=0.01)
    assert sim.observe()["actions"][0, 0].tolist() == [KEEP, KEEP, KEEP, applied]


def test_a_lane_change_in_a_frame_the_rule_brakes_is_decelerate_and_still_changes_lanes():
    # His player: the change starts (switch_lane), then car.move("M") finds no "M" behind the
    # slower car and the recorded action is "D"; the car is in the new lane within the frame
    # and brakes on over the skipped frames.
    sim = ho_sim([Car(dx=9.5, lane=OWN_LANE, speed_kmh=60.0)], ego_speed_kmh=90.0)
    result = sim.step(np.array([[LANE_LEFT]]))
    assert int(result.action_applied[0, 0]) == CRUISE_DOWN
    assert sim.state.lane[0, 0] == OWN_LANE + 1 and sim.metrics()["lane_changes"][0, 0] == 1
    assert speed_kmh(sim) == pytest.approx(57.0, abs=0.01)
    assert sim.observe()["actions"][0, 0, -1] == CRUISE_DOWN
    # As chosen (the setting off): the lane change is what was applied.
    chosen = ho_sim([Car(dx=9.5, lane=OWN_LANE, speed_kmh=60.0)], ego_speed_kmh=90.0, **AS_CHOSEN)
    assert step_applied(chosen, LANE_LEFT) == LANE_LEFT
    assert speed_kmh(chosen) == pytest.approx(60.0, abs=0.01)


def test_a_braked_lane_change_opposite_to_a_recent_one_still_costs_the_alternation():
    # His car.py reads the change chosen (the player's ``result``) against the stack of
    # actions as driven: a change right, then, braked by the rule, a change left.
    # 5.5 m bumper to bumper in the lane on the right: beyond the gap in the change's frame,
    # matched at the decision's last.
    sim = ho_sim([Car(dx=12.5, lane=OWN_LANE - 1, speed_kmh=60.0)], ego_speed_kmh=90.0)
    assert step_applied(sim, LANE_RIGHT) == LANE_RIGHT
    assert speed_kmh(sim) == pytest.approx(60.0, abs=0.01)
    sim.state.speed_mps[0, 1] = 30.0 * KMH  # the car it is now behind brakes hard
    result = sim.step(np.array([[LANE_LEFT]]))
    assert int(result.action_applied[0, 0]) == CRUISE_DOWN
    assert float(result.reward_terms["alternation"][0, 0]) == pytest.approx(-0.00001)
    assert sim.observe()["actions"][0, 0].tolist() == [KEEP, KEEP, LANE_RIGHT, CRUISE_DOWN]


def test_the_action_stack_holds_the_actions_as_driven():
    sim = ho_sim([Car(dx=9.5, lane=OWN_LANE, speed_kmh=60.0)], ego_speed_kmh=90.0)
    chosen = (CRUISE_UP, KEEP, CRUISE_UP, LANE_RIGHT)
    applied = [step_applied(sim, action) for action in chosen]
    # Braked to 60 (and on to 57) behind it; then kept behind it, an accelerate within the
    # gap kept too; the change right onto a free lane as chosen.
    assert applied == [CRUISE_DOWN, KEEP, KEEP, LANE_RIGHT]
    assert sim.observe()["actions"][0, 0].tolist() == applied


def test_applied_as_driven_is_his_speed_steps_and_a_record_from_before_replays_without_it():
    from overtake.server.sim.config import as_json
    from overtake.server.sim.settings_history import as_recorded

    assert make_config("ho2018").ego.applied_as_driven
    assert not make_config("ho2018", AS_CHOSEN).ego.applied_as_driven
    with pytest.raises(ValueError, match="ego.applied_as_driven"):
        make_config("min2018", {"ego.applied_as_driven": True})
    # A record made before the setting existed (issue 66) lacks it: its simulator applied the
    # action chosen.
    recorded = as_json(make_config("ho2018"))
    del recorded["ego"]["applied_as_driven"]
    assert not as_recorded("ho2018", {}, recorded).ego.applied_as_driven


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
    # Left, then right once the change is over (within its first frame), while
    # the left is still among the last four actions; then right again, with no left among them.
    for action in (LANE_LEFT, KEEP, KEEP, KEEP, LANE_RIGHT, KEEP, KEEP, KEEP, KEEP, LANE_RIGHT):
        result = sim.step(np.array([[action]]))
        assert result.action_applied[0, 0] == action
        rewards.append(float(result.reward_terms["alternation"][0, 0]))
    assert rewards[4] == pytest.approx(-0.00001)
    assert rewards[:4] + rewards[5:] == [0.0] * 9


# --- the road (Table 4) -------------------------------------------------------------------------


class RoadCensus:
    """Samples which behaviour each car on the road has, every tenth decision of a run."""

    def __init__(self, envs) -> None:
        self.sim = envs.unwrapped.sim
        self.kinds: list[np.ndarray] = []
        self.steps = 0

    def started(self, obs, info) -> None:
        pass

    def stepped(self, step) -> None:
        self.steps += 1
        if self.steps % 10 == 0:
            st = self.sim.state
            self.kinds.append(st.kind[:, 1:][st.active[:, 1:]])

    def shares(self) -> np.ndarray:
        kinds = np.concatenate(self.kinds)
        return np.bincount(kinds, minlength=3)[:3] / kinds.size


# Ho's own code (gui.py's loop, his car.py and players) with this rule driver as its subject,
# evaluated as he evaluates (a decision every frame, 4,000 frames): 86.8 km/h in medium traffic
# and 72.1 in heavy over 80 episodes each; the behaviours' shares of the cars on his road 0.30
# / 0.30 / 0.40 and 0.33 / 0.33 / 0.33; 37.7 of 39 and 55.5 of 59 traffic cars on it
# (bench/RESULTS.md).
@pytest.mark.parametrize(
    "density,speed_kmh,tolerance_kmh,cars",
    [
        ("medium", 87.0, 3.0, 39),
        # Heavy traffic's 80 episodes take 7 s of the default suite's time: -m slow runs them.
        pytest.param("heavy", 73.0, 4.0, 59, marks=pytest.mark.slow),
    ],
)
def test_the_rule_driver_drives_as_fast_as_in_his_code_among_his_traffic(
    density, speed_kmh, tolerance_kmh, cars
):
    from overtake.trainers.config.presets import PRESET_TRAINING

    evaluation = dict(item.split("=") for item in PRESET_TRAINING["ho2018"].evaluation)
    assert evaluation == {"episode.frames_per_decision": "1", "episode.max_decisions": "4000"}
    episodes = 40
    envs = Where().open(
        "ho2018",
        {
            "traffic.density": density,
            "episode.frames_per_decision": 1,
            "episode.max_decisions": 4000,
        },
        episodes,
    )
    act = baseline_policy("rule", envs.behaviour_spec, 0, episodes, envs)
    census = RoadCensus(envs)
    rows, _, _ = run_episodes(envs, act, episodes, 1000, watchers=[census])
    envs.close()
    speed = np.mean([row["avg_speed_kmh"] for row in rows])
    assert abs(speed - speed_kmh) <= tolerance_kmh, speed
    assert np.abs(census.shares() - 1 / 3).max() <= 0.1, census.shares()
    # The road holds about as many cars as his does: nearly all of Table 4's.
    on_road = np.mean([row["traffic_cars"] for row in rows])
    assert 0.88 * cars <= on_road <= cars
    assert all(row["collisions"] == 0 for row in rows)


def test_ho_s_traffic_does_not_collide_with_random_driving():
    sim = HighwaySim(make_config("ho2018", {"traffic.density": "heavy"}), num_arenas=4)
    sim.reset(seeds=[5, 6, 7, 8])
    rng = np.random.default_rng(1)
    kinds = set()
    for _ in range(300):
        assert not sim.step(rng.integers(0, 5, size=(4, 1))).terminated.any()
        kinds |= set(sim.state.kind[:, 1:][sim.state.active[:, 1:]].tolist())
    assert kinds == {0, 1, 2}  # steady, road maximum, lane switcher: all three on the road


def test_the_road_starts_with_the_agent_alone_and_fills_by_his_entry_rule():
    sim = HighwaySim(make_config("ho2018", {"traffic.density": "medium"}), num_arenas=2)
    sim.reset(seeds=[1, 2])
    assert not sim.state.active[:, 1:].any()
    counts = []
    for _ in range(200):
        sim.step(np.full((2, 1), KEEP))
        counts.append(sim.state.active[:, 1:].sum(axis=1))
    # At most one car a frame (four a decision), with probability one half each.
    entries = np.diff(np.array(counts), axis=0)
    assert entries.max() <= 4
    assert np.array(counts)[-1].min() >= 20


# Every lane's entry zone behind the agent, and every lane's but lane 2's ahead of it, holds a
# car moving with the agent (60 km/h); lane 2 has one just outside its zone, 11 m behind the
# entry point 80 m ahead: no room by the IDM's comfort, room by Ho's rule.
ZONES_BLOCKED = [Car(dx=-31.0, lane=lane, speed_kmh=60.0) for lane in range(7)] + [
    Car(dx=80.0 if lane != 2 else 69.0, lane=lane, speed_kmh=60.0) for lane in range(7)
]


def test_a_car_enters_where_its_lanes_entry_zone_is_free_whatever_the_gaps():
    sim = ho_sim(
        ZONES_BLOCKED,
        **{
            "traffic.vehicle_count": len(ZONES_BLOCKED) + 1,
            "episode.frames_per_decision": 1,
        },
    )
    st, new = sim.state, len(ZONES_BLOCKED) + 1
    assert not st.active[0, new]
    # The comfortable spawner would not place a car there: the one 11 m behind is too close.
    assert not sim.spawner.clearance_ok(
        st,
        np.array([0]),
        np.array([[2]]),
        np.array([[80.0]]),
        np.array([[45.0 * KMH]]),
        np.array([[0]]),
        st.active[[0]],
    )[0, 0]
    for _ in range(200):  # a try a frame, at one half, ahead at one half
        keep(sim)
        if st.active[0, new]:
            break
    assert st.active[0, new]
    assert st.lane[0, new] == 2
    assert st.x_m[0, new] - st.x_m[0, 0] == pytest.approx(80.0, abs=0.5)
    entry_kmh = float(st.speed_mps[0, new]) / KMH
    own_kmh = float(st.own_speed_mps[0, new]) / KMH
    assert 30.0 <= entry_kmh <= 60.0 + 1.0 and 50.0 <= own_kmh <= 100.0
    assert st.desired_speed_mps[0, new] / KMH >= own_kmh - 1e-9
    # Nothing collides, whatever the gap it entered into.
    assert not any(keep(sim).terminated[0, 0] for _ in range(100))


def test_his_cars_hold_the_speed_the_car_ahead_left_them_and_wander_to_100():
    # A steady car (own speed 50 km/h) slowed to 55 km/h behind a slower car keeps 55 once
    # that car is gone; a "stick to max" car from 70 km/h wanders within 70-100 km/h.
    sim = ho_sim(
        [
            Car(dx=30.0, lane=0, speed_kmh=55.0, kind=STEADY, desired_kmh=80.0),
            Car(dx=30.0, lane=6, speed_kmh=70.0, kind=ROAD_MAX),
        ],
        ego_lane=3,
        ego_speed_kmh=60.0,
        **{
            "traffic.steady.keeps_current_speed": True,
            "traffic.road_max.keeps_current_speed": True,
            "traffic.road_max.speed_steps_per_s": 12.5,
            "traffic.road_max.speed_step_up_prob": 1 / 3,
            "traffic.road_max.speed_step_down_prob": 1 / 3,
            "traffic.keep_ahead_m": 5000.0,
            "traffic.keep_behind_m": 5000.0,
            "episode.frames_per_decision": 1,
        },
    )
    st = sim.state
    st.own_speed_mps[0, 1] = 50.0 * KMH
    st.own_speed_mps[0, 2] = 70.0 * KMH
    wandered = []
    for _ in range(3000):
        keep(sim)
        wandered.append(float(st.speed_mps[0, 2]) / KMH)
    assert float(st.speed_mps[0, 1]) / KMH == pytest.approx(55.0)
    assert min(wandered) >= 70.0 - 1e-6 and max(wandered) <= 100.0 + 1e-6
    assert max(wandered) >= 90.0  # it wanders, up to near the road's maximum


def test_traffic_follows_his_rule_and_takes_a_slower_cars_speed_at_once():
    # A car at 100 km/h closes on one at 50: it keeps its speed until it is within 3 m bumper
    # to bumper (traffic.safety_gap_m), then takes 50 at once, and never comes nearer.
    sim = ho_sim(
        [
            Car(dx=20.0, lane=0, speed_kmh=100.0, kind=STEADY),
            Car(dx=60.0, lane=0, speed_kmh=50.0, kind=STEADY),
        ],
        ego_lane=4,
        ego_speed_kmh=60.0,
        **{"traffic.keep_ahead_m": 5000.0, "episode.frames_per_decision": 1},
    )
    st = sim.state
    speeds, gaps = [], []
    for _ in range(60):
        keep(sim)
        speeds.append(float(st.speed_mps[0, 1]) / KMH)
        gaps.append(float(st.x_m[0, 2] - st.x_m[0, 1]) - 7.0)
    # A frame's rule reads the gap the frame starts with (the one the frame before left).
    first_slow = next(i for i, v in enumerate(speeds) if v < 99.9)
    assert speeds[first_slow] == pytest.approx(50.0)  # no braking before: matched at once
    assert gaps[first_slow - 2] >= 3.0 and gaps[first_slow - 1] < 3.0
    assert min(gaps) > 0.0 and speeds[-1] == pytest.approx(50.0)


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
        envs = Where().open("ho2018", short, 3)
        act = baseline_policy(policy, envs.behaviour_spec, 0, 3, envs)
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
    envs = Where().open("ho2018", {"grid.side_lanes": 2}, 1)
    with pytest.raises(UsageError, match="grid.side_lanes = 2"):
        baseline_policy("rule", envs.behaviour_spec, 0, 1, envs)
    envs.close()


def test_evaluation_decides_every_frame_as_his_code_does():
    """Ho's code skips frames only while training (gui.py): overtake-eval drives his 4,000
    frames with a decision at each, and --no-paper-evaluation as in training, 1,000 decisions
    of 4 frames; both the same 320 s of road."""
    from overtake.trainers.evaluate import EvalConfig
    from overtake.trainers.evaluate import main as evaluate

    # An empty road: idle driving covers the same distance in the same time either way.
    empty = ("traffic.vehicle_count=0",)
    every_frame = evaluate(
        EvalConfig(policy="idle", episodes=1, scenario=Scenario(preset="ho2018", set=empty))
    )
    as_trained = evaluate(
        EvalConfig(
            policy="idle",
            episodes=1,
            paper_evaluation=False,
            scenario=Scenario(preset="ho2018", set=empty),
        )
    )
    assert every_frame["overrides"]["episode.frames_per_decision"] == 1
    assert [row["decisions"] for row in every_frame["episodes"]] == [4000]
    assert [row["decisions"] for row in as_trained["episodes"]] == [1000]
    distance = [r["episodes"][0]["distance_m"] for r in (every_frame, as_trained)]
    assert distance[0] == pytest.approx(distance[1], rel=1e-9)
    assert distance[0] == pytest.approx(60.0 * KMH * 320.0)
