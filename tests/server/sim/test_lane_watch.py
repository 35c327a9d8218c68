"""Driver assistance that watches a lane change through (issue 46, ``ego.lane_change_watch``):
scripted scenes, each of which ends in a collision without the watch and in none with it."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from overtake.client.episodes.scenario import Scenario
from overtake.protocol.vocabulary import KEEP, LANE_LEFT, WATCH_METRICS
from overtake.server.sim import HighwaySim, make_config
from overtake.server.sim.units import KMH

from tests.support.scenes import HALF_LENGTH, Car, scripted_sim

Hook = Callable[[HighwaySim, int], None]


def drive(
    cars: list[Car],
    *,
    watch: bool,
    hook: Hook | None = None,
    ego_speed_kmh: float = 60.0,
    decisions: int = 25,
    overrides: dict | None = None,
) -> tuple[HighwaySim, list[int]]:
    """The agent in lane 2 asks for a change left at the first decision, then keeps; ``hook``
    changes the scene before decision ``d``. Returns the simulation at the end (or at the
    collision) and the actions applied."""
    sim = scripted_sim(
        cars,
        ego_lane=2,
        ego_speed_kmh=ego_speed_kmh,
        # The start check of the authors' DAS off: what is tested is the watch alone.
        overrides={
            "ego.lane_change_watch": watch,
            "ego.lane_change_check": False,
            **(overrides or {}),
        },
    )
    applied = []
    for d in range(decisions):
        if hook is not None:
            hook(sim, d)
        result = sim.step(np.full((1, 1), LANE_LEFT if d == 0 else KEEP))
        applied.append(int(result.action_applied[0, 0]))
        if result.terminated[0, 0]:
            break
    return sim, applied


def metric(sim: HighwaySim, name: str) -> float:
    return float(sim.metrics()[name][0, 0])


def starts_into_lane_3(at: int, column: int = 1) -> Hook:
    """Traffic car ``column`` starts a change into lane 3 before decision ``at``."""

    def hook(sim: HighwaySim, d: int) -> None:
        if d == at:
            sim.state.target_lane[0, column] = 3
            sim.state.change_progress[0, column] = 0.0

    return hook


def drops_to(at: int, speed_kmh: float, column: int = 1) -> Hook:
    """Traffic car ``column`` is at ``speed_kmh`` (and wants no more) from decision ``at``."""

    def hook(sim: HighwaySim, d: int) -> None:
        if d == at:
            sim.state.speed_mps[0, column] = speed_kmh * KMH
            sim.state.desired_speed_mps[0, column] = speed_kmh * KMH

    return hook


@pytest.mark.parametrize("watch", [False, True])
def test_a_fast_car_closing_in_the_target_lane_turns_the_change_back(watch):
    """A car 25 m behind in the target lane speeds up to 120 km/h after the change began:
    without the watch the agent completes the change and is run into; with it the change turns
    back before the marking and the fast car passes."""
    sim, _ = drive(
        [Car(-25.0, 3, 60.0)], watch=watch, hook=drops_to(1, 120.0)
    )  # "drops to" a higher speed: the car behind accelerates hard
    if not watch:
        assert metric(sim, "collisions") == 1.0
        return
    assert metric(sim, "collisions") == 0.0
    assert metric(sim, "lane_change_aborts") == 1.0
    assert sim.state.lane[0, 0] == sim.state.target_lane[0, 0] == 2  # back in its lane
    assert sim.state.x_m[0, 1] > sim.state.x_m[0, 0]  # the fast car went by


@pytest.mark.parametrize("watch", [False, True])
def test_a_leader_braking_hard_before_the_marking_turns_the_change_back(watch):
    """The target lane's leader, 20 m ahead, drops to 5 km/h while the agent is 20% through
    its change: turned back, the agent stays behind its own lane's free road."""
    sim, _ = drive([Car(20.0, 3, 60.0)], watch=watch, hook=drops_to(1, 5.0))
    assert metric(sim, "collisions") == (0.0 if watch else 1.0)
    if watch:
        assert metric(sim, "lane_change_aborts") == 1.0
        assert sim.state.lane[0, 0] == 2 and sim.state.x_m[0, 0] > sim.state.x_m[0, 1]


@pytest.mark.parametrize("watch", [False, True])
def test_two_cars_changing_into_one_gap_from_both_sides_meet_no_more(watch):
    """Issue 34's 29 collisions: a car two lanes over, 2 m behind and a little faster, starts
    into the same lane one decision after the agent; the agent turns back."""
    sim, _ = drive([Car(-2.0, 4, 70.0)], watch=watch, hook=starts_into_lane_3(1))
    assert metric(sim, "collisions") == (0.0 if watch else 1.0)
    if watch:
        assert metric(sim, "lane_change_aborts") == 1.0
        assert sim.state.lane[0, 0] == 2 and sim.state.lane[0, 1] == 3


def test_a_change_into_a_lane_another_car_is_entering_alongside_does_not_start():
    """The same meeting when the other car began first (as in all 29): the change the agent
    asks for is refused, and the action applied is keep."""
    sim, applied = drive([Car(-2.0, 4, 70.0)], watch=True, hook=starts_into_lane_3(0), decisions=3)
    assert applied[0] == KEEP
    assert metric(sim, "lane_changes") == 0.0 and metric(sim, "lane_change_aborts") == 0.0
    assert sim.state.target_lane[0, 0] == 2


@pytest.mark.parametrize("watch", [False, True])
def test_past_the_marking_the_change_completes_and_the_fail_safe_brakes(watch):
    """At 110 km/h, when the agent is 60% through its change, the target lane's leader 60 m
    ahead drops to 10 km/h: nothing turns back now. Emergency braking alone (at a time to
    collision of 1.5 s) starts too late; the fail-safe brakes as hard as the gap needs from the
    first frame, and the agent stops behind it in its new lane."""
    sim, _ = drive(
        [Car(60.0, 3, 110.0)],
        watch=watch,
        hook=drops_to(3, 10.0),
        ego_speed_kmh=110.0,
        decisions=40,
        overrides={"ego.cruise_max_kmh": 130.0},
    )
    assert metric(sim, "collisions") == (0.0 if watch else 1.0)
    if watch:
        assert metric(sim, "lane_change_aborts") == 0.0
        assert sim.state.lane[0, 0] == 3  # completed
        gap = sim.state.x_m[0, 1] - sim.state.x_m[0, 0] - 2 * HALF_LENGTH
        assert gap >= sim.config.ego.min_gap_m - 0.5


def test_the_rule_s_distances():
    """Safe exactly where the follower, reacting after 0.4 s and braking at 3 m/s^2, keeps
    2 m: a car 10 m/s faster behind needs 2 + 4 + 16.7 m, bumper to bumper."""
    needed = 2.0 + 10.0 * 0.4 + 10.0**2 / (2 * 3.0)
    for gap, safe in ((needed + 0.05, True), (needed - 0.05, False)):
        sim = scripted_sim(
            [Car(-(gap + 2 * HALF_LENGTH), 3, 60.0 + 36.0)],
            overrides={"ego.lane_change_watch": True},
        )
        st = sim.state
        st.target_lane[0, 0] = 3
        assert sim.lane_changes.watch.unsafe(st)[0, 0] == (not safe)
    # Same speed: only the standstill gap; alongside: never.
    for dx, safe in ((2 * HALF_LENGTH + 2.1, True), (2 * HALF_LENGTH + 1.9, False), (0.0, False)):
        sim = scripted_sim([Car(dx, 3, 60.0)], overrides={"ego.lane_change_watch": True})
        sim.state.target_lane[0, 0] = 3
        assert sim.lane_changes.watch.unsafe(sim.state)[0, 0] == (not safe)


def test_a_free_road_drives_the_same_with_the_watch():
    """With nobody to watch, the watch changes nothing: the same positions and speeds."""
    runs = []
    for watch in (False, True):
        sim, applied = drive([Car(200.0, 0, 60.0)], watch=watch, decisions=15)
        runs.append((sim.state.x_m[0, 0], sim.state.y_m[0, 0], sim.state.speed_mps[0, 0]))
        assert applied[0] == LANE_LEFT
    assert runs[0] == runs[1]


def test_the_watch_adds_its_metric_and_is_off_in_every_paper_preset():
    from overtake.server.sim import PRESETS

    for preset in PRESETS:
        config = make_config(preset)
        assert not config.ego.lane_change_watch
        assert HighwaySim(config, num_arenas=1).metric_fields[-len(WATCH_METRICS) :] != (
            WATCH_METRICS
        )
    watched = HighwaySim(make_config("min2018", {"ego.lane_change_watch": True}), num_arenas=1)
    assert watched.metric_fields[-len(WATCH_METRICS) :] == WATCH_METRICS


# --- what the learner makes of it ------------------------------------------------------------


class _Shield:
    """Stands in for the training shield: it overrode the greedy choice where ``flags``."""

    def __init__(self, flags: list[bool]) -> None:
        self.flags, self.overrides = np.array(flags), 0

    def count(self, q, env_mask, mask) -> np.ndarray:
        self.overrides += int(self.flags.sum())
        return self.flags


def test_the_replay_stores_what_the_car_did_and_pays_where_safety_stepped_in():
    from overtake.trainers.learning.learner import DQNConfig
    from overtake.trainers.run.shielding import SafetyLayer

    envs = np.arange(4)
    shield = _Shield([False, False, True, False])
    layer = SafetyLayer(shield, DQNConfig(store_applied=True, intervention_penalty=0.5), 4)
    assert layer.count(envs, None, None, None) == 1 and layer.overrides == 1
    counts = {"collisions": np.zeros(4, dtype=np.int64)}

    def step(applied, aborts):
        info = {
            "action_applied": np.array(applied),
            "episode_counts": {**counts, "lane_change_aborts": np.array(aborts)},
        }
        return layer.stored(envs, np.array([3, 3, 4, 2]), np.ones(4), info)

    # env 0: its lane change refused (stored as keep, penalised); env 2: the shield overrode it;
    # env 3: a change of its turned back in this step.
    stored, reward = step([0, 3, 4, 2], [0, 0, 0, 1])
    assert stored.tolist() == [0, 3, 4, 2]
    assert reward.tolist() == [0.5, 1.0, 0.5, 0.5]
    # The same count again is no new abort; an autoreset step (-1) stores the chosen action.
    layer.overridden[:] = False
    stored, reward = step([-1, 3, 4, 2], [0, 0, 0, 1])
    assert stored.tolist() == [3, 3, 4, 2] and reward.tolist() == [1.0] * 4
    # Off (the defaults): what was chosen, as it was rewarded.
    plain = SafetyLayer(None, DQNConfig(), 4)
    stored, reward = plain.stored(
        envs, np.array([3, 3, 4, 2]), np.ones(4), {"action_applied": np.array([0, 3, 4, 2])}
    )
    assert stored.tolist() == [3, 3, 4, 2] and reward.tolist() == [1.0] * 4


def test_a_late_action_replaced_by_keep_is_stored_as_keep_and_not_penalised():
    from overtake.trainers.learning.learner import DQNConfig
    from overtake.trainers.run.shielding import SafetyLayer

    layer = SafetyLayer(None, DQNConfig(store_applied=True, intervention_penalty=0.5), 2)
    info = {"action_applied": np.array([KEEP, KEEP]), "late": np.array([True, False])}
    stored, reward = layer.stored(np.arange(2), np.array([LANE_LEFT, LANE_LEFT]), np.ones(2), info)
    # Both cars kept their lane; only the second had its action refused by safety.
    assert stored.tolist() == [KEEP, KEEP] and reward.tolist() == [1.0, 0.5]


def test_the_logged_reward_is_what_the_driving_earned_not_the_penalised_reward(tmp_path):
    """Two runs alike but for the learner's intervention penalty, stopped before learning
    starts (so they drive the same random episodes): the training log's rewards are equal,
    because the penalty changes what is learned from, not what the driving earned."""
    import json

    from overtake.trainers.learning.learner import DQNConfig
    from overtake.trainers.train import TrainConfig
    from overtake.trainers.train import main as train

    logged = {}
    for penalty in (0.0, 1.0):
        run_dir = tmp_path / f"penalty{penalty}"
        train(
            TrainConfig(
                inputs="lidar",
                num_envs=2,
                total_steps=60,
                log_every=30,
                seed=4,
                run_dir=run_dir,
                progress=False,
                dqn=DQNConfig(
                    learning_starts=1000,
                    replay_size=500,
                    lstm_cells=8,
                    store_applied=True,
                    intervention_penalty=penalty,
                ),
                scenario=Scenario(set=("traffic.density=heavy",)),
            )
        )
        lines = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
        logged[penalty] = [line["reward_sum"] for line in lines if line.get("kind") == "train"]
    assert logged[0.0] and logged[0.0] == logged[1.0]


def test_the_shield_s_watch_is_a_simulator_setting_of_the_run_and_its_row():
    from overtake.trainers.config.train_config import TrainConfig
    from overtake.trainers.experiment import EXPERIMENTS

    assert TrainConfig(shield=True, shield_watch=True).overrides()["ego.lane_change_watch"]
    assert "ego.lane_change_watch" not in TrainConfig(shield=True).overrides()
    rows = {row.label: row for row in EXPERIMENTS["min2018-safe"].rows}
    assert rows["watch"].shield_watch and rows["watch"].store_applied
    assert not rows["shield"].shield_watch  # issue 34's rows as they were


def test_a_run_with_the_watch_trains_and_its_evaluation_keeps_the_watch(tmp_path):
    """--shield-watch trains (the applied actions stored, a penalty where safety stepped in)
    and its checkpoint's evaluation runs with the watch: the aborts are a column."""
    from overtake.trainers.evaluate import EvalConfig
    from overtake.trainers.evaluate import main as evaluate
    from overtake.trainers.learning.learner import DQNConfig
    from overtake.trainers.run.checkpoint import CHECKPOINT_NAME, load_checkpoint
    from overtake.trainers.train import TrainConfig
    from overtake.trainers.train import main as train

    run_dir = tmp_path / "run"
    train(
        TrainConfig(
            inputs="lidar",
            num_envs=2,
            total_steps=160,
            shield=True,
            shield_watch=True,
            seed=2,
            run_dir=run_dir,
            progress=False,
            dqn=DQNConfig(
                learning_starts=40,
                replay_size=1000,
                target_update_steps=50,
                lstm_cells=8,
                store_applied=True,
                intervention_penalty=0.1,
            ),
            scenario=Scenario(set=("episode.max_decisions=50", "traffic.density=heavy")),
        )
    )
    checkpoint = load_checkpoint(run_dir / CHECKPOINT_NAME)
    assert checkpoint.overrides["ego.lane_change_watch"] is True
    assert checkpoint.dqn.store_applied and checkpoint.dqn.intervention_penalty == 0.1
    result = evaluate(
        EvalConfig(
            checkpoint=run_dir / CHECKPOINT_NAME, episodes=2, scenario=Scenario(max_decisions=30)
        )
    )
    assert all("lane_change_aborts" in row for row in result["episodes"])
    assert "lane_change_aborts" in result["summary"]
    # Without the shield its second half goes too, as in overtake-drive: no watch, no aborts.
    bare = evaluate(
        EvalConfig(
            checkpoint=run_dir / CHECKPOINT_NAME,
            episodes=2,
            shield=False,
            scenario=Scenario(max_decisions=30),
        )
    )
    assert "lane_change_aborts" not in bare["summary"]
    assert "shield_overrides" not in bare["summary"]


def test_the_experiments_report_safety_per_episode_and_per_km():
    from overtake.protocol.vocabulary import METRIC_FIELDS
    from overtake.trainers.experiment.statistics import episode_statistics

    def episode(distance_m, aborts, overrides):
        row = dict.fromkeys(METRIC_FIELDS, 1.0)
        return {
            **row,
            "distance_m": distance_m,
            "lane_change_aborts": aborts,
            "shield_overrides": overrides,
        }

    stats = episode_statistics([episode(2000.0, 1.0, 10.0), episode(500.0, 1.0, 0.0)])
    assert stats["lane_change_aborts"]["mean"] == 1.0
    assert stats["lane_change_aborts_per_km"]["mean"] == pytest.approx((0.5 + 2.0) / 2)
    assert stats["shield_overrides_per_km"]["mean"] == pytest.approx((5.0 + 0.0) / 2)
    plain = episode_statistics([dict.fromkeys(METRIC_FIELDS, 1.0)])
    assert "lane_change_aborts" not in plain and "shield_overrides_per_km" not in plain


def test_the_fail_safe_brakes_only_the_agent_that_needs_it():
    """One arena's agent closes fast on a slow car; the other's road is free: only the first
    one's acceleration is lowered, the other keeps accelerating as without the watch."""
    from tests.support.scenes import CALM_TRAFFIC, place

    overrides = {**CALM_TRAFFIC, "traffic.vehicle_count": 1, "ego.lane_change_watch": True}
    sim = HighwaySim(make_config("min2018", overrides=overrides), num_arenas=2)
    sim.reset(seeds=[0, 1])
    for arena, car_x in ((0, HALF_LENGTH * 2 + 8.0), (1, 400.0)):
        place(sim, 0, x=0.0, lane=2, speed_kmh=60.0, arena=arena)
        place(sim, 1, x=car_x, lane=2, speed_kmh=10.0, arena=arena)
    accel = np.full(sim.state.x_m.shape, 1.5)
    watch = sim.physics.watch
    assert watch is not None
    watch.frame(sim.state, accel)
    assert accel[0, 0] < -sim.config.ego.comfort_decel_mps2  # braking hard behind the slow car
    assert accel[1, 0] == 1.5  # the free road: untouched
    assert (accel[:, 1:] == 1.5).all()  # and traffic is not the watch's


def test_the_watch_is_refused_where_speed_steps_set_the_speed():
    """Ho's speed steps set the agent's speed each frame: the fail-safe brake, which lowers
    cruise control's acceleration, would do nothing there, so the two are not combined."""
    from overtake.server.sim import ConfigError

    with pytest.raises(ConfigError, match="speed_steps"):
        make_config("ho2018", overrides={"ego.lane_change_watch": True})
