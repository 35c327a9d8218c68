"""Min et al.'s set-up as the paper describes it: cruise actions from the current speed, warnings
that are observed and cost when ignored, random traffic up to its density, emergency brakes
per decision, and the reference policies (idle, planner)."""

from __future__ import annotations

import dataclasses

import gymnasium as gym
import numpy as np
import pytest

import overtake.client  # noqa: F401  (registers the environments)
from overtake.cli import UsageError
from overtake.client.episodes.runner import baseline_policy, run_episodes
from overtake.client.episodes.scenario import Where
from overtake.envs import HIGHWAY_ENV_ID
from overtake.envs.faces import VectorFace
from overtake.protocol.vocabulary import CRUISE_DOWN, CRUISE_UP, KEEP, LANE_LEFT, LANE_RIGHT
from overtake.server.sim import HighwaySim, make_config
from overtake.server.sim.physics import traffic_overlaps
from overtake.server.sim.planner import Planner
from overtake.server.sim.units import KMH

from tests.support.scenes import Car, keep, place, scripted_sim

LEFT, RIGHT, FORWARD = range(3)


def warnings_of(sim: HighwaySim) -> list[bool]:
    return sim.warnings.compute(sim.state)[0, 0].tolist()


# --- actions (§II.C) ---------------------------------------------------------------------------


def test_cruise_actions_set_the_target_from_the_current_speed():
    sim = scripted_sim([], ego_lane=2, ego_speed_kmh=60.0, cruise_kmh=80.0)
    st = sim.state
    sim.step(np.array([[CRUISE_UP]]))
    speed_before = float(st.speed_mps[0, 0])
    assert st.desired_speed_mps[0, 0] > speed_before  # v + 5 km/h, chased at once
    sim.step(np.array([[KEEP]]))
    # Keep: cruise control holds the speed the car has now (not the 80 km/h it started with).
    assert st.desired_speed_mps[0, 0] == pytest.approx(float(st.speed_mps[0, 0]), abs=0.3)
    held = float(st.speed_mps[0, 0])
    for _ in range(10):
        keep(sim)
    assert st.speed_mps[0, 0] == pytest.approx(held, abs=1e-6)
    sim.step(np.array([[CRUISE_DOWN]]))
    assert st.speed_mps[0, 0] < held


def test_up_is_a_5_kmh_step_over_the_speed_the_car_has():
    sim = scripted_sim([], ego_lane=2, ego_speed_kmh=60.0)
    st = sim.state
    before = float(st.speed_mps[0, 0])
    # The target is set before the decision's frames, from the speed at its start.
    sim.actions.apply(st, np.array([[CRUISE_UP]]))
    assert st.desired_speed_mps[0, 0] == pytest.approx(before + 5.0 * KMH)
    sim.actions.apply(st, np.array([[CRUISE_DOWN]]))
    assert st.desired_speed_mps[0, 0] == pytest.approx(before - 5.0 * KMH)


def test_a_slowdown_sticks_until_the_agent_accelerates_and_the_remembered_variant_returns():
    # A slow car ahead changes lanes away after the ego has slowed down behind it.
    def after_the_slow_car_leaves(mode: str) -> float:
        sim = scripted_sim(
            [Car(25.0, 2, 45.0)],
            ego_lane=2,
            ego_speed_kmh=80.0,
            cruise_kmh=80.0,
            overrides={"ego.cruise_mode": mode},
        )
        st = sim.state
        for _ in range(25):
            keep(sim)
        place(sim, 1, x=float(st.x_m[0, 1]), lane=4, speed_kmh=45.0)
        for _ in range(40):
            keep(sim)
        return float(st.speed_mps[0, 0]) / KMH

    assert after_the_slow_car_leaves("current") < 50.0
    assert after_the_slow_car_leaves("remembered") == pytest.approx(80.0, abs=0.5)


# --- warnings (the authors' code) --------------------------------------------------------------


def test_side_and_forward_warnings():
    assert warnings_of(scripted_sim([], ego_lane=2)) == [False, False, False]
    # A car beside on the left; no lane right of lane 0.
    assert warnings_of(scripted_sim([Car(0.0, 1, 60.0)], ego_lane=0)) == [True, True, False]
    # A slower car 20 m ahead at 72 km/h is within 2 s (+2 m): a forward warning; a faster
    # one is not, nor a slower one far ahead.
    assert warnings_of(scripted_sim([Car(20.0, 2, 50.0)], ego_speed_kmh=72.0))[FORWARD]
    assert not warnings_of(scripted_sim([Car(20.0, 2, 90.0)], ego_speed_kmh=72.0))[FORWARD]
    assert not warnings_of(scripted_sim([Car(60.0, 2, 50.0)], ego_speed_kmh=72.0))[FORWARD]


def test_the_car_refuses_a_change_against_a_side_warning_and_the_attempt_still_costs():
    # The authors' DAS (VehicleAgent.cs): no lane change under a side warning. The mask offers
    # the change (the agent chooses among all five); the car keeps its lane, says so, pays the
    # warning term and no lane-change term, and nothing collides.
    sim = scripted_sim([Car(0.0, 3, 60.0)], ego_lane=2)
    assert sim.action_mask()[0, 0, LANE_LEFT] == 1
    result = sim.step(np.array([[LANE_LEFT]]))
    assert result.action_applied[0, 0] == KEEP
    assert result.reward_terms["warning"][0, 0] == -0.1
    assert result.reward_terms["lane_change"][0, 0] == 0.0
    assert sim.state.target_lane[0, 0] == 2
    assert not any(keep(sim).terminated[0, 0] for _ in range(6))


def test_with_the_check_off_a_change_against_a_side_warning_starts_costs_and_can_collide():
    sim = scripted_sim([Car(0.0, 3, 60.0)], ego_lane=2, overrides={"ego.lane_change_check": False})
    assert sim.action_mask()[0, 0, LANE_LEFT] == 1
    result = sim.step(np.array([[LANE_LEFT]]))
    assert result.action_applied[0, 0] == LANE_LEFT
    assert result.reward_terms["warning"][0, 0] == -0.1
    assert result.reward_terms["lane_change"][0, 0] == -0.25
    collided = False
    for _ in range(6):
        collided |= bool(keep(sim).terminated[0, 0])
    assert collided


def test_accelerating_against_a_forward_warning_costs_and_heeding_it_does_not():
    def first_decision(action: int) -> float:
        sim = scripted_sim([Car(20.0, 2, 50.0)], ego_lane=2, ego_speed_kmh=72.0)
        return float(sim.step(np.array([[action]])).reward_terms["warning"][0, 0])

    assert first_decision(CRUISE_UP) == -0.1
    assert first_decision(KEEP) == 0.0
    assert first_decision(LANE_RIGHT) == 0.0  # the right side is clear


def test_the_mask_carries_the_refusals_only_when_asked_to():
    sim = scripted_sim([Car(0.0, 3, 60.0)], ego_lane=2, overrides={"ego.mask_refusals": True})
    assert sim.action_mask()[0, 0, LANE_LEFT] == 0
    assert sim.action_mask()[0, 0, LANE_RIGHT] == 1
    assert sim.step(np.array([[LANE_LEFT]])).action_applied[0, 0] == KEEP


def test_the_kept_warnings_are_those_of_the_state_after_every_change_of_it():
    """The state keeps the warnings the agents are shown (worked out once per decision); they
    must be what the state says after decisions of all or some arenas, resets, respawns and
    cars taken off and put back, and what the ego vector shows."""
    sim = HighwaySim(make_config(), num_arenas=3, agents_per_arena=2)
    sim.reset(seeds=[1, 2, 3])
    rng = np.random.default_rng(0)

    def assert_current() -> None:
        fresh = sim.warnings.compute(sim.state)
        np.testing.assert_array_equal(sim.state.warnings, fresh)
        ego = sim.observe()["ego"]
        fields = sim.config.ego_vector.fields
        for i, name in enumerate(("left_warning", "right_warning", "forward_warning")):
            np.testing.assert_array_equal(ego[..., fields.index(name)], fresh[..., i])

    assert_current()
    assert sim.state.warnings.any()  # the check means something: some agent is warned
    for decision in range(60):
        if decision % 3 == 2:
            rows = np.array([0, 2])
            result = sim.step(rng.integers(5, size=(2, 2)), arenas=rows)
        else:
            rows = np.arange(3)
            result = sim.step(rng.integers(5, size=(3, 2)))
        assert_current()
        ended = result.terminated | result.truncated
        for row, slot in zip(*np.nonzero(ended), strict=True):
            sim.respawn_agents(int(rows[row]), [int(slot)])
            assert_current()
        if decision % 10 == 5:  # a respawn moves the car: its own warnings change
            sim.respawn_agents(0, [0])
            assert_current()
        if decision == 20:
            # Agent 1 right beside agent 0 (a side warning), then off the road and back.
            st = sim.state
            lane = int(st.lane[1, 0])
            beside = lane + 1 if lane < 4 else lane - 1
            place(sim, 1, x=float(st.x_m[1, 0]), lane=beside, speed_kmh=60.0, arena=1)
            assert sim.state.warnings[1, 0, LEFT if beside > lane else RIGHT]
            sim.remove_agents(1, [1])
            assert_current()
            sim.restore_agents(1, [1])
            assert_current()
        if decision == 40:
            sim.reset([1], seeds=[9])
            assert_current()


# --- traffic (§IV.A) ---------------------------------------------------------------------------


def test_random_traffic_changes_lanes_for_no_reason_and_safely():
    def lane_changes(rate: float) -> int:
        overrides = {
            "traffic.density": "heavy",
            "camera.enabled": False,
            "lidar.enabled": False,
            # No change ever pays by MOBIL's incentive: only random ones remain.
            "traffic.random.lane_change_threshold_mps2": 10.0,
            "traffic.random.random_lane_change_rate_per_s": rate,
        }
        sim = HighwaySim(make_config(overrides=overrides), num_arenas=4)
        sim.reset(seeds=[0, 1, 2, 3])
        st = sim.state
        changes = 0
        for _ in range(150):
            idle = st.target_lane[:, 1:] == st.lane[:, 1:]
            keep(sim)
            # Changes started this decision (a recycled car starts with none under way).
            changes += int((idle & (st.target_lane[:, 1:] != st.lane[:, 1:])).sum())
            # Random changes are taken only where safe: traffic never overlaps traffic.
            assert not traffic_overlaps(sim.state, sim.kinds, sim.agents).any()
        return changes

    assert lane_changes(0.0) == 0
    assert lane_changes(0.2) > 20


def test_traffic_speeds_step_5_kmh_every_5_s_mostly_up_from_40_60_towards_80():
    """The authors' TargetMovement.cs: a car starts at 40-60 km/h and every 5 s (the scene's
    random-action slider at 3) steps 5 km/h, up with probability 0.75, within 40-80."""
    arenas, decisions = 8, 600
    sim = HighwaySim(
        make_config(
            overrides={
                "camera.enabled": False,
                "lidar.enabled": False,
                "traffic.density": "heavy",
                # Nobody leaves the road: every car walks for the whole run.
                "traffic.keep_ahead_m": 5000.0,
                "traffic.keep_behind_m": 5000.0,
            }
        ),
        num_arenas=arenas,
    )
    sim.reset(seeds=list(range(arenas)))
    st = sim.state
    starts, ups, downs, held, steps_of_5 = [], 0, 0, 0, True
    own = st.own_speed_mps[:, 1:].copy()
    desired = st.desired_speed_mps[:, 1:].copy()
    starts.append(desired[st.active[:, 1:]] / KMH)
    for _ in range(decisions):
        keep(sim)
        new_own, new_desired = st.own_speed_mps[:, 1:], st.desired_speed_mps[:, 1:]
        same_car = (new_own == own) & st.active[:, 1:]
        entered = (new_own != own) & st.active[:, 1:]
        starts.append(new_desired[entered] / KMH)
        change = (new_desired - desired)[same_car] / KMH
        moved = change[np.abs(change) > 1e-9]
        # Every step is 5 km/h (or what is left of it to the bounds).
        steps_of_5 &= bool(np.all((np.abs(np.abs(moved) - 5.0) < 1e-6) | (np.abs(moved) < 5.0)))
        inside = same_car & (desired > 45.5 * KMH) & (desired < 74.5 * KMH)
        inner = (new_desired - desired)[inside] / KMH
        ups += int((inner > 1e-9).sum())
        downs += int((inner < -1e-9).sum())
        held += int(inside.sum())
        own, desired = new_own.copy(), new_desired.copy()
    starts = np.concatenate(starts)
    assert starts.min() >= 40.0 - 1e-9 and starts.max() <= 60.0 + 1e-9
    assert steps_of_5
    final = st.desired_speed_mps[:, 1:][st.active[:, 1:]] / KMH
    assert final.min() >= 40.0 - 1e-9 and final.max() <= 80.0 + 1e-9
    # Up three times in four; a step every 5 s on average (a decision is 0.4 s).
    assert ups / (ups + downs) == pytest.approx(0.75, abs=0.04)
    assert (ups + downs) / held == pytest.approx(0.4 / 5.0, rel=0.12)
    # So traffic drifts towards the 80 km/h the host may drive: after 4 minutes most cars want
    # 70-80 km/h.
    assert np.median(final) >= 70.0


@pytest.mark.parametrize("density, cars", [("light", 10), ("medium", 20), ("heavy", 32)])
@pytest.mark.parametrize("entry", ["spawners", "comfortable"])
def test_each_density_is_the_most_cars_on_the_road_and_the_treadmill_holds_it(density, cars, entry):
    """The authors' spawners (the preset) keep at most the slider's count, and the road holds
    fewer as cars come and go (tests/server/sim/test_spawners.py); the treadmill holds it."""
    envs = Where().open(
        "min2018",
        {
            "traffic.density": density,
            "traffic.entry": entry,
            "camera.enabled": False,
            "episode.max_decisions": 150,
        },
        4,
    )
    rows, _, _ = run_episodes(envs, lambda o, i, s: np.full(4, CRUISE_UP), 4, 0)
    envs.close()
    on_road = np.mean([row["traffic_cars"] for row in rows])
    if entry == "comfortable":
        assert cars * 0.9 <= on_road <= cars
    else:
        assert cars * 0.5 <= on_road < cars


def test_random_driving_crashes_only_without_the_authors_lane_change_check():
    # Driving at random is dangerous where the car changes lanes blindly: collisions and
    # emergency brakes happen. With the authors' DAS beneath, the same episodes do not crash.
    def collisions_and_brakes(check: bool) -> tuple[float, float]:
        envs = Where().open(
            "min2018",
            {
                "camera.enabled": False,
                "episode.max_decisions": 400,
                "ego.lane_change_check": check,
            },
            16,
        )
        act = baseline_policy("random", envs.behaviour_spec, 0, 16, envs)
        rows, _, _ = run_episodes(envs, act, 16, 100)
        envs.close()
        return (
            sum(row["collisions"] for row in rows),
            sum(row["emergency_brakes"] for row in rows),
        )

    blind_collisions, blind_brakes = collisions_and_brakes(False)
    assert blind_collisions >= 8 and blind_brakes >= 1
    assert collisions_and_brakes(True)[0] == 0


# --- reference policies ------------------------------------------------------------------------


def test_the_planner_passes_a_slow_car_where_the_side_is_free_and_waits_where_it_is_not():
    slow = Car(25.0, 2, 45.0)
    sim = scripted_sim([slow], ego_lane=2, ego_speed_kmh=80.0, calm=True)
    assert Planner(sim).act()[0, 0] in (LANE_LEFT, LANE_RIGHT)
    # Cars alongside on both sides: no change (it would collide), and no acceleration into
    # the slow car ahead (its forward warning).
    boxed = scripted_sim(
        [slow, Car(0.0, 1, 80.0), Car(0.0, 3, 80.0)], ego_lane=2, ego_speed_kmh=80.0
    )
    assert Planner(boxed).act()[0, 0] == KEEP
    # A free road: accelerate to the limit.
    free = scripted_sim([], ego_lane=2, ego_speed_kmh=60.0)
    assert Planner(free).act()[0, 0] == CRUISE_UP


def test_idle_and_planner_are_reference_policies_in_process_only_for_the_planner():
    envs = Where().open("min2018", {"camera.enabled": False}, 2)
    idle = baseline_policy("idle", envs.behaviour_spec, 0, 2, envs)
    assert idle({}, {}, np.ones(2, dtype=bool)).tolist() == [KEEP, KEEP]
    obs, info = envs.reset(seed=0)
    planner = baseline_policy("planner", envs.behaviour_spec, 0, 2, envs)
    actions = planner(obs, info, np.ones(2, dtype=bool))
    assert actions.shape == (2,) and actions.dtype == np.int64
    # A simulator with no road to read (as a remote one): the planner is refused.
    remote_like = VectorFace(dataclasses.replace(envs.simulator, road=None), 2)
    with pytest.raises(UsageError, match="in-process"):
        baseline_policy("planner", envs.behaviour_spec, 0, 2, remote_like)
    envs.close()
    single = gym.make(HIGHWAY_ENV_ID, overrides={"camera.enabled": False})
    single.reset(seed=0)
    assert single.unwrapped.planner_action() in range(5)
    single.close()
