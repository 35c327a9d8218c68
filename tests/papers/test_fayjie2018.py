"""Fayjie et al.'s set-up (2018) as the ``fayjie2018`` preset: the RGB camera and the LIDAR as
an 80x80 grid map, a reward per action and -6 for a hit, and nothing that brakes for the
agent."""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import pytest

import overtake.client  # noqa: F401  (registers the environments)
from overtake.client.episodes.scenario import Scenario, Where
from overtake.envs import HIGHWAY_ENV_ID
from overtake.protocol.vocabulary import CRUISE_DOWN, CRUISE_UP, KEEP, LANE_LEFT, LANE_RIGHT
from overtake.server.sim import HighwaySim, make_config
from overtake.server.sim.units import KMH

from tests.support.scenes import Car, keep, scripted_sim

OWN_LANE = 2


def fayjie_sim(cars=(), *, ego_speed_kmh=60.0, **overrides) -> HighwaySim:
    return scripted_sim(
        list(cars),
        ego_lane=OWN_LANE,
        ego_speed_kmh=ego_speed_kmh,
        preset="fayjie2018",
        overrides=overrides,
    )


def test_the_preset_observes_the_rgb_camera_and_the_lidar_map():
    env = gym.make(HIGHWAY_ENV_ID, preset="fayjie2018")
    space = env.observation_space
    assert sorted(space.spaces) == ["camera", "lidar_map"]
    assert space["camera"].shape == (80, 80, 3) and space["lidar_map"].shape == (80, 80)
    obs, _ = env.reset(seed=2)
    assert space.contains(obs)
    env.close()


def test_the_lidar_map_draws_the_returns_where_they_are():
    # A car 10 m ahead in the agent's lane: its rear bumper 7.75 m ahead is row
    # floor((40 - 7.75) / 0.5) = 64, across the car's 1.8 m width about columns 38-41. The guard
    # rails, 9.75 m either side of the centre of lane 2 of 5, are columns 20 and 59.
    sim = fayjie_sim([Car(dx=10.0, lane=OWN_LANE, speed_kmh=60.0)])
    image = sim.observe()["lidar_map"][0, 0]
    assert set(np.unique(image).tolist()) == {0, 255}
    assert (image[64, 38:42] == 255).all()
    assert not image[:64, 30:50].any() and not image[66:, 30:50].any()  # nothing else ahead
    assert image[:, 20].sum() > 0 and image[:, 59].sum() > 0
    assert not image[:, 21:30].any() and not image[:, 50:59].any()
    empty = fayjie_sim().observe()["lidar_map"][0, 0]
    assert not empty[:, 30:50].any()


@pytest.mark.parametrize(
    "action,reward",
    [
        (KEEP, 0.2 * 60.0 * KMH),  # keep going: the speed (m/s) / 5
        (CRUISE_UP, 1.0),
        (CRUISE_DOWN, -0.4),
        (LANE_LEFT, -0.6),
        (LANE_RIGHT, -0.2),
    ],
)
def test_each_action_has_its_reward(action, reward):
    sim = fayjie_sim()
    result = sim.step(np.array([[action]]))
    assert result.action_applied[0, 0] == action
    assert result.reward[0, 0] == pytest.approx(reward)
    assert result.reward_terms["collision"][0, 0] == 0.0


def test_nothing_brakes_for_the_agent_a_hit_costs_6_and_ends_the_episode():
    sim = fayjie_sim([Car(dx=20.0, lane=OWN_LANE, speed_kmh=20.0)], ego_speed_kmh=80.0)
    results = [keep(sim) for _ in range(12)]
    hit = next(i for i, r in enumerate(results) if r.terminated[0, 0])
    assert results[hit].reward_terms["collision"][0, 0] == -6.0
    assert all(r.reward_terms["collision"][0, 0] == 0.0 for r in results[:hit])
    # Braking in time avoids it: 1 km/h per 0.1 s frame (2.8 m/s^2) closes 60 km/h in 6 s and
    # 50 m, less than the 55.5 m between the bumpers.
    careful = fayjie_sim([Car(dx=60.0, lane=OWN_LANE, speed_kmh=20.0)], ego_speed_kmh=80.0)
    assert not any(careful.step(np.array([[CRUISE_DOWN]])).terminated[0, 0] for _ in range(20))
    assert float(careful.state.speed_mps[0, 0]) / KMH < 21.0


@pytest.mark.parametrize("density,cars", [("light", 5), ("medium", 10), ("heavy", 20)])
def test_the_density_holds_its_cars(density, cars):
    sim = HighwaySim(make_config("fayjie2018", {"traffic.density": density}), num_arenas=4)
    sim.reset(seeds=[1, 2, 3, 4])
    for _ in range(200):
        sim.step(np.zeros((4, 1), dtype=np.int64))
    assert sim.metrics()["traffic_cars"].mean() >= 0.9 * cars


# --- training (§III.A, Table I) -----------------------------------------------------------------


def test_the_two_stream_network_has_three_convolutions_per_stream_and_four_dense_layers():
    import torch

    from overtake.trainers.learning.two_stream_network import TwoStreamQNetwork, TwoStreamShape

    network = TwoStreamQNetwork(TwoStreamShape((80, 80, 3), (80, 80), 5, 4))
    for stream in (network.camera, network.lidar_map):
        assert sum(isinstance(m, torch.nn.Conv2d) for m in stream) == 3
        assert sum(isinstance(m, torch.nn.MaxPool2d) for m in stream) == 3
    dense = [m for m in network.modules() if isinstance(m, torch.nn.Linear)]
    assert len(dense) == 5  # one per stream, then 3 on the fused path: 4 on each input's way
    camera = torch.randint(0, 256, (2, 4, 80, 80, 3), dtype=torch.uint8)
    lidar_map = torch.randint(0, 256, (2, 4, 80, 80), dtype=torch.uint8)
    assert network(camera, lidar_map).shape == (2, 5)
    # Each stream matters.
    assert not torch.equal(network(camera, lidar_map), network(camera, lidar_map.flip(0)))
    assert not torch.equal(network(camera, lidar_map), network(camera.flip(0), lidar_map))


def test_training_on_the_preset_uses_table_i_and_its_checkpoint_evaluates(tmp_path):
    from overtake.trainers.evaluate import EvalConfig
    from overtake.trainers.evaluate import main as evaluate
    from overtake.trainers.run.checkpoint import CHECKPOINT_NAME, load_checkpoint
    from overtake.trainers.train import COMMAND as train_command

    run_dir = tmp_path / "run"
    train_command.run(
        ["--preset", "fayjie2018", "--run-dir", str(run_dir), "--total-steps", "80"]
        + ["--num-envs", "2", "--learning-starts", "40", "--torch-threads", "1", "--no-progress"]
        + ["--sink", "off", "--set", "episode.max_decisions=30"]
    )
    checkpoint = load_checkpoint(run_dir / CHECKPOINT_NAME)
    assert (checkpoint.algo, checkpoint.inputs) == ("dqn", "camera-map")
    dqn = checkpoint.dqn
    assert (dqn.network, dqn.learning_rate, dqn.gamma) == ("two-stream", 0.001, 0.99)
    assert (dqn.replay_size, dqn.batch_size, dqn.target_update_steps) == (15_000, 32, 6_000)
    result = evaluate(
        EvalConfig(
            checkpoint=run_dir / CHECKPOINT_NAME, episodes=2, scenario=Scenario(max_decisions=10)
        )
    )
    assert result["preset"] == "fayjie2018" and result["summary"]["episodes"] == 2


def test_the_fig6_experiment_keeps_table_i_and_sums_the_reward_per_3000_steps(tmp_path):
    from overtake.cli import UsageError
    from overtake.trainers.experiment import ExperimentConfig, make_plan, window_rewards

    plan = make_plan(ExperimentConfig(experiment="fayjie2018-fig6", out=tmp_path))
    [run] = plan.runs
    assert run.train.preset == "fayjie2018" and run.train.inputs == "camera-map"
    # Table I as it is (the paper trained about this long), and a training line per window.
    assert (run.train.dqn.replay_size, run.train.dqn.target_update_steps) == (15_000, 6_000)
    assert run.train.log_every == 3_000 and plan.total_steps >= 100_000
    with pytest.raises(UsageError, match="plots no reward per window"):
        make_plan(ExperimentConfig(experiment="min2018-table3", reward_window_steps=10))
    records = {
        "a": [{"step": 3001, "reward_sum": 4.0}, {"step": 6002, "reward_sum": 10.0}],
        "b": [{"step": 3000, "reward_sum": 2.0}, {"step": 6000, "reward_sum": None}],
    }
    # Each point is a reward per 3,000 steps: run a's first line covers 3,001.
    a1, a2 = 4.0 * 3_000 / 3_001, 10.0 * 3_000 / 3_001
    assert window_rewards(records, 3_000) == {
        "window_end_step": [3_000, 6_000],
        "mean": [pytest.approx((a1 + 2.0) / 2), pytest.approx(a2)],
        "run_min": [2.0, pytest.approx(a2)],
        "run_max": [pytest.approx(a1), pytest.approx(a2)],
    }


def test_a_short_window_before_a_stop_or_at_the_budget_is_neither_a_dip_nor_a_second_run():
    from overtake.trainers.experiment import window_rewards

    rate = 3.0  # reward per step, all along

    def run(lines: list[tuple[int, int]], from_step: bool = True) -> list[dict[str, Any]]:
        return [
            {"step": end, "reward_sum": rate * (end - begin)}
            | ({"from_step": begin} if from_step else {})
            for begin, end in lines
        ]

    # Stopped (SIGTERM) at 3,695 just after its line at 3,000, resumed there; the budget ends
    # at 7,000, 305 steps after the line at 6,695.
    lines = [(0, 3_000), (3_000, 3_695), (3_695, 6_695), (6_695, 7_000)]
    for records in (run(lines), run(lines, from_step=False)):
        curve = window_rewards({"a": records}, 3_000)
        # The stop's short line joins the next (6,695 -> 6,000), and so does the budget's,
        # whose nearest multiple is that point's.
        assert curve["window_end_step"] == [3_000, 6_000]
        assert curve["mean"] == [pytest.approx(rate * 3_000)] * 2
    # A longer last line is a point of its own, at its rate.
    curve = window_rewards({"a": run([*lines[:3], (6_695, 8_900)])}, 3_000)
    assert curve["window_end_step"] == [3_000, 6_000, 9_000]
    assert curve["mean"] == [pytest.approx(rate * 3_000)] * 3
    # Resumed from a checkpoint older than its last line (kill -9): the first line of the new
    # life covers from the checkpoint, which only from_step tells.
    resumed = run([(0, 3_000), (2_000, 5_000), (5_000, 8_000)])
    curve = window_rewards({"a": resumed}, 3_000)
    assert curve["mean"] == [pytest.approx(rate * 3_000)] * 3


# --- the rule-based driver on the LIDAR map -----------------------------------------------------


def blank_map() -> np.ndarray:
    return np.zeros((1, 80, 80), dtype=np.uint8)


def car_at(image: np.ndarray, ahead_m: float, left_m: float) -> None:
    """Draw a car's rear bumper row, 1.8 m wide, as the map would."""
    row = int((40.0 - ahead_m) / 0.5)
    columns = slice(int((20.0 - left_m - 0.9) / 0.5), int((20.0 - left_m + 0.9) / 0.5) + 1)
    image[0, row, columns] = 255


@pytest.mark.parametrize(
    "cars,expected",
    [
        ([], CRUISE_UP),  # nothing in sight
        ([(36.0, 0.0)], KEEP),  # something far ahead: keep going
        ([(20.0, 0.0), (20.0, 3.5), (20.0, -3.5)], CRUISE_DOWN),  # blocked everywhere
        ([(20.0, 0.0), (30.0, -3.5)], LANE_LEFT),  # the left lane is free
        ([(20.0, 0.0), (30.0, 3.5)], CRUISE_DOWN),  # left not 15 m better, right taken below
        ([(20.0, 0.0), (5.0, 3.5)], LANE_RIGHT),  # a car just ahead on the left
    ],
)
def test_the_map_rule_driver_keeps_its_distance_and_changes_to_a_freer_lane(cars, expected):
    from overtake.client.policies.drivers import MapRuleDriver

    image = blank_map()
    if expected == CRUISE_DOWN and len(cars) == 2:
        car_at(image, 25.0, -3.5)  # and the lane to the right no better
    for ahead, left in cars:
        car_at(image, ahead, left)
    assert MapRuleDriver().act(image, np.ones((1, 5), dtype=np.int8)).tolist() == [expected]


def test_the_rule_driver_drives_fayjie2018_from_its_map():
    from overtake.client.episodes.runner import baseline_policy, run_episodes

    envs = Where().open("fayjie2018", {"traffic.density": "light"}, 2)
    act = baseline_policy("rule", envs.behaviour_spec, 0, 2, envs)
    rows, _, _ = run_episodes(envs, act, 2, 1000)
    envs.close()
    assert all(row["avg_speed_kmh"] > 80.0 for row in rows)  # idle holds 60, random about 55


def test_fig6_draws_what_never_acting_earns_per_3000_steps_beside_the_curve(tmp_path):
    """Fayjie et al.'s reward pays for keeping going: the curve's reference is what the idle
    driver earns per 3,000 steps, its evaluation's reward per decision in the training
    traffic times the window."""
    from types import SimpleNamespace

    from overtake.trainers.experiment import ExperimentConfig, make_plan
    from overtake.trainers.experiment.curves import plot_curves
    from overtake.trainers.experiment.report import Outputs

    config = ExperimentConfig(experiment="fayjie2018-fig6", out=tmp_path)
    plan = make_plan(config)
    idle = SimpleNamespace(key={"policy": "idle", "density": "medium"})
    episodes = [{"return": 300.0, "decisions": 100.0}, {"return": 500.0, "decisions": 100.0}]
    run = SimpleNamespace(
        reference_tasks=lambda: [idle], cached=lambda task: {"episodes": episodes}
    )
    outputs = Outputs(config, plan, run)  # type: ignore[arg-type]
    assert outputs._never_acting(3_000) == pytest.approx(800.0 / 200.0 * 3_000)
    # And the plot draws it as a line of its own on the reward panel.
    curves = {
        "dqn": {
            "runs": 1,
            "bin_end_step": [3_000, 6_000],
            **{m: {"mean": [1.0, 2.0]} for m in ("avg_speed_kmh", "return")},
            "window_reward": {"window_end_step": [3_000, 6_000], "mean": [5_000.0, 9_000.0]},
            "window_reference": {"never acting (idle)": 12_000.0},
        }
    }
    plot_curves(curves, "fig6", tmp_path / "curves.png")
    assert (tmp_path / "curves.png").stat().st_size > 0
    no_reference = {"dqn": {**curves["dqn"]}}
    del no_reference["dqn"]["window_reference"]
    plot_curves(no_reference, "fig6", tmp_path / "plain.png")
    assert (tmp_path / "curves.png").read_bytes() != (tmp_path / "plain.png").read_bytes()
