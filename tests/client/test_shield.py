"""The safety shield (overtake.client.policies.shield): what it masks on scenes built to tempt a
driver, that it reads only what the car observes, and where it refuses to run."""

from __future__ import annotations

import numpy as np
import pytest

from overtake.cli import UsageError
from overtake.client.episodes.scenario import Scenario, Where
from overtake.client.policies.shield import Shield, overridden
from overtake.protocol.vocabulary import CRUISE_DOWN, CRUISE_UP, KEEP, LANE_LEFT, LANE_RIGHT
from overtake.server.engine.env import HighwayEnv

from tests.support.scenes import Car, keep, scripted_sim

OWN = 2  # the middle of min2018's five lanes
SPEC = HighwayEnv().behaviour_spec


def judged(cars: tuple[Car, ...], ego_kmh: float = 50.0) -> np.ndarray:
    """The shield's verdict (actions,) on a scene after one decision of keeping the lane: the
    two scans it stacks are those of the scene and of the decision after."""
    sim = scripted_sim(cars, ego_lane=OWN, ego_speed_kmh=ego_kmh)
    first = sim.observe()
    keep(sim)
    second = sim.observe()
    lidar = np.stack([first["lidar"][0, 0], second["lidar"][0, 0]])[None]
    return Shield(SPEC).mask(lidar, second["ego"][0])[0]


def test_a_clear_road_allows_everything():
    assert judged(()).tolist() == [1] * 5


def test_a_car_alongside_forbids_changing_into_its_lane_only():
    allowed = judged((Car(dx=0.0, lane=OWN + 1, speed_kmh=50.0),))
    assert allowed[LANE_LEFT] == 0  # lanes count from the right: OWN + 1 is the left one
    assert allowed[[KEEP, CRUISE_UP, CRUISE_DOWN, LANE_RIGHT]].tolist() == [1, 1, 1, 1]


def test_a_fast_car_behind_forbids_the_change_a_slow_one_at_the_same_gap_allows():
    # 20 m behind in the right lane (15.5 m bumper to bumper): at the car's own 50 km/h the
    # gap is more than the 2 m + 0.5 s of time gap; closing at 50 km/h it is far too little.
    closing = judged((Car(dx=-20.0, lane=OWN - 1, speed_kmh=100.0),))
    level = judged((Car(dx=-20.0, lane=OWN - 1, speed_kmh=50.0),))
    assert closing[LANE_RIGHT] == 0 and level[LANE_RIGHT] == 1
    assert closing[LANE_LEFT] == 1 and level[LANE_LEFT] == 1


def test_a_slow_car_close_ahead_forbids_accelerating_not_braking():
    allowed = judged((Car(dx=12.0, lane=OWN, speed_kmh=30.0),), ego_kmh=60.0)
    assert allowed[CRUISE_UP] == 0 and allowed[CRUISE_DOWN] == 1 and allowed[KEEP] == 1
    far = judged((Car(dx=70.0, lane=OWN, speed_kmh=60.0),), ego_kmh=60.0)
    assert far[CRUISE_UP] == 1


def test_the_shield_reads_what_the_car_observes_not_the_state():
    """Moving a car outside every LIDAR ray's reach changes nothing the shield says, though
    the simulator's state changes: it decides from the observation alone."""
    near = scripted_sim((Car(dx=0.0, lane=OWN + 1, speed_kmh=50.0),), ego_lane=OWN)
    obs = near.observe()
    shield = Shield(SPEC)
    stacked = np.repeat(obs["lidar"][:, 0][:, None], 2, axis=1)
    verdict = shield.mask(stacked, obs["ego"][:, 0])
    near.state.x_m[0, 1] += 500.0  # the car is gone from the road ahead of any scan ...
    assert (shield.mask(stacked, obs["ego"][:, 0]) == verdict).all()  # ... not from this scan
    assert verdict[0, LANE_LEFT] == 0


def test_an_unsafe_greedy_choice_is_counted_as_overridden():
    q = np.array([[0.0, 0.1, 0.2, 9.0, 0.3], [5.0, 0.0, 0.0, 0.0, 0.0]])
    env_mask = np.ones((2, 5), dtype=np.int8)
    shield_mask = np.ones((2, 5), dtype=np.int8)
    shield_mask[:, LANE_LEFT] = 0
    assert overridden(q, env_mask, shield_mask).tolist() == [True, False]
    # The network's choice among what the environment allows: a left change the environment
    # refuses is not the shield's override.
    env_mask[0, LANE_LEFT] = 0
    assert overridden(q, env_mask, shield_mask).tolist() == [False, False]


@pytest.mark.parametrize(
    ("preset", "overrides", "says"),
    [
        ("ho2018", {}, r"preset ho2018's agents observe actions, grid, without a LIDAR scan"),
        ("fayjie2018", {}, r"without a LIDAR scan .* and the car's speed"),
        ("min2018", {"ego_vector.fields": ["left_warning"]}, r"without the car's speed"),
    ],
)
def test_presets_without_a_scan_or_the_cars_speed_are_refused_saying_why(preset, overrides, says):
    spec = HighwayEnv(preset=preset, overrides=overrides).behaviour_spec
    with pytest.raises(UsageError, match=says):
        Shield(spec)


def test_training_behind_the_shield_counts_its_overrides_and_evaluation_keeps_it(tmp_path):
    import json

    from overtake.trainers.evaluate import EvalConfig
    from overtake.trainers.evaluate import main as evaluate
    from overtake.trainers.learning.learner import DQNConfig
    from overtake.trainers.run.checkpoint import CHECKPOINT_NAME
    from overtake.trainers.train import TrainConfig
    from overtake.trainers.train import main as train

    run_dir = tmp_path / "run"
    summary = train(
        TrainConfig(
            inputs="lidar",
            num_envs=2,
            total_steps=300,
            shield=True,
            seed=1,
            run_dir=run_dir,
            progress=False,
            log_every=100,
            dqn=DQNConfig(
                learning_starts=60, replay_size=2000, target_update_steps=100, lstm_cells=16
            ),
            scenario=Scenario(set=("episode.max_decisions=60",)),
        )
    )
    assert summary["shield_overrides"] > 0
    lines = [json.loads(x) for x in (run_dir / "metrics.jsonl").read_text().splitlines()]
    logged = [line["shield_overrides"] for line in lines if line["kind"] == "train"]
    assert sum(logged) == summary["shield_overrides"]
    checkpoint = run_dir / CHECKPOINT_NAME
    shielded = evaluate(
        EvalConfig(checkpoint=checkpoint, episodes=2, scenario=Scenario(max_decisions=40))
    )
    assert all("shield_overrides" in row for row in shielded["episodes"])
    assert "shield_overrides" in shielded["summary"]
    bare = evaluate(
        EvalConfig(
            checkpoint=checkpoint, episodes=2, shield=False, scenario=Scenario(max_decisions=40)
        )
    )
    assert "shield_overrides" not in bare["summary"]
    # Exported, the model says it was trained behind the shield, and the ONNX driver puts it
    # in front of the model as evaluation does: the same decisions, the same overrides.
    from overtake.client.episodes.drive import DriveConfig
    from overtake.client.episodes.drive import main as drive
    from overtake.client.episodes.runner import run_episodes
    from overtake.client.policies.onnx_policy import OnnxPolicy, read_metadata
    from overtake.trainers.export import ExportConfig
    from overtake.trainers.export import main as export

    onnx = tmp_path / "policy.onnx"
    export(ExportConfig(checkpoint=checkpoint, out=onnx, check_decisions=0))
    assert read_metadata(onnx)["shield"] is True
    overrides = {"episode.max_decisions": 40, "camera.enabled": False}
    envs = Where().open("min2018", overrides, 2)
    policy = OnnxPolicy(onnx, 2, envs.single_observation_space, "min2018", spec=envs.behaviour_spec)
    rows, _, _ = run_episodes(envs, policy, 2, 1000)
    envs.close()
    by_eval = {row["shield_overrides"] for row in shielded["episodes"]}
    assert {row["shield_overrides"] for row in rows} == by_eval
    driven = drive(
        DriveConfig(onnx=onnx, episodes=2, seed=1000, scenario=Scenario(max_decisions=40))
    )
    assert "shield_overrides" in driven


def test_training_behind_the_shield_on_a_preset_it_cannot_read_is_refused(tmp_path):
    from overtake.trainers.train import TrainConfig
    from overtake.trainers.train import main as train

    with pytest.raises(UsageError, match="LIDAR scan"):
        train(TrainConfig.for_preset("ho2018", shield=True, total_steps=8, run_dir=tmp_path))
