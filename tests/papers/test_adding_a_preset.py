"""Adding a paper's preset is its simulator and its training (docs/development.md, "To add
something"; its experiment, golden digest and page are the other three files): done here
once with a two-lane road, which is then served in process and by a server's group, trained
with its own defaults, and evaluated from its checkpoint, with no other change."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from overtake.client.episodes.scenario import Scenario
from overtake.server.engine.env import HighwayVectorEnv
from overtake.server.service.groups import Group
from overtake.server.sim import PRESETS, make_config
from overtake.trainers.config.presets import PRESET_TRAINING, PresetTraining
from overtake.trainers.config.train_config import TrainConfig
from overtake.trainers.evaluate import EvalConfig
from overtake.trainers.evaluate import main as evaluate
from overtake.trainers.learning.dqn_config import DQNConfig
from overtake.trainers.run.checkpoint import CHECKPOINT_NAME, load_checkpoint
from overtake.trainers.train import main as train

NAME = "twolane2026"


def two_lanes():
    """The preset's simulator: min2018's, on two lanes, with a few cars and short episodes."""
    base = make_config("min2018", {"traffic.vehicle_count": 3, "episode.max_decisions": 30})
    return dataclasses.replace(base, preset=NAME, road=dataclasses.replace(base.road, lane_count=2))


@pytest.fixture
def preset(monkeypatch):
    monkeypatch.setitem(PRESETS, NAME, two_lanes)
    tiny = DQNConfig(
        learning_starts=40, replay_size=500, target_update_steps=50, epsilon_decay_steps=100
    )
    monkeypatch.setitem(PRESET_TRAINING, NAME, PresetTraining("ddqn", "lidar", tiny))
    return NAME


@pytest.mark.timeout(120)
def test_a_new_preset_is_served_trained_and_evaluated(preset, tmp_path):
    envs = HighwayVectorEnv(2, preset)
    try:
        assert envs.behaviour_spec.road is not None
        assert envs.behaviour_spec.road.lane_count == 2
        envs.reset(seed=1)
        envs.step(np.zeros(2, np.int64))
    finally:
        envs.close()
    group = Group.open(0, "srv", [0], preset, {}, 1, seed=1)
    assert group.spec.preset == preset and group.spec.road.lane_count == 2

    config = TrainConfig.for_preset(preset, run_dir=tmp_path / "run", total_steps=120)
    assert (config.algo, config.inputs, config.dqn.learning_starts) == ("ddqn", "lidar", 40)
    summary = train(dataclasses.replace(config, progress=False, checkpoint_every=120))
    assert summary["steps"] >= 120
    checkpoint = load_checkpoint(tmp_path / "run" / CHECKPOINT_NAME)
    assert checkpoint.preset == preset
    result = evaluate(
        EvalConfig(
            checkpoint=tmp_path / "run" / CHECKPOINT_NAME,
            episodes=1,
            scenario=Scenario(max_decisions=5),
        )
    )
    assert result["preset"] == preset and len(result["episodes"]) == 1
