"""Training on ``ho2018`` with no further flags: the preset's own algorithm, inputs, network,
optimiser and hyper-parameters (Table 6), every one overridable; its checkpoints evaluate on
Ho's set-up and are refused, naming both presets, on Min et al.'s (and the other way round)."""

from __future__ import annotations

import json
from dataclasses import replace

import pytest

from overtake.cli import UsageError
from overtake.client.episodes.scenario import Scenario, parse_overrides
from overtake.server.sim import make_config
from overtake.trainers.evaluate import EvalConfig
from overtake.trainers.evaluate import main as evaluate
from overtake.trainers.experiment import (
    ExperimentConfig,
    check_directory,
    make_plan,
    training_identity,
)
from overtake.trainers.learning.grid_network import GridQNetwork
from overtake.trainers.learning.learner import DQNConfig
from overtake.trainers.learning.tf_rmsprop import TFRMSprop
from overtake.trainers.run.checkpoint import CHECKPOINT_NAME, load_checkpoint
from overtake.trainers.train import COMMAND as train_command
from overtake.trainers.train import TrainConfig, preset_in
from overtake.trainers.train import main as train

SMALL = [
    "--total-steps", "160", "--num-envs", "2", "--learning-starts", "48", "--replay-size", "600",
    "--log-every", "80", "--checkpoint-every", "80", "--torch-threads", "1", "--no-progress",
    "--set", "episode.max_decisions=40", "--sink", "off",
]  # fmt: skip


@pytest.fixture(scope="module")
def ho_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("ho") / "run"
    train_command.run(["--preset", "ho2018", "--run-dir", str(run_dir), *SMALL])
    return run_dir


def test_the_preset_names_its_training(ho_run):
    checkpoint = load_checkpoint(ho_run / CHECKPOINT_NAME)
    assert (checkpoint.algo, checkpoint.inputs, checkpoint.preset) == ("dqn", "grid", "ho2018")
    dqn = checkpoint.dqn
    assert (dqn.network, dqn.optimizer, dqn.loss) == ("proposed", "tf-rmsprop", "mse")
    assert dqn.learning_rate == 0.0005 and dqn.rmsprop_alpha == 0.9 and dqn.gamma == 0.99
    assert dqn.rmsprop_eps == 1e-10 and not dqn.rmsprop_centered and dqn.train_every == 1
    assert dqn.epsilon_decay_steps == 2_000_000 and dqn.target_update_steps == 10_000
    # His loop: the action his car drove stored, the time limit's end terminal, his start.
    assert dqn.store_applied and not dqn.bootstrap_time_limit
    assert (dqn.init, dqn.init_std) == ("truncated-normal", 0.02)
    # What the command line said still wins over the preset's.
    assert dqn.learning_starts == 48 and dqn.replay_size == 600
    learner = checkpoint.make_learner()
    assert isinstance(learner.online, GridQNetwork) and learner.online.kind == "proposed"
    assert isinstance(learner.optimizer, TFRMSprop)
    run = json.loads((ho_run / "run.json").read_text())
    assert run["sim_config"]["grid"]["enabled"] and not run["sim_config"]["lidar"]["enabled"]
    assert run["sim_config"]["ego"]["applied_as_driven"]
    assert checkpoint.step >= 160


def test_its_checkpoint_evaluates_on_ho2018(ho_run, tmp_path):
    result = evaluate(
        EvalConfig(
            checkpoint=ho_run / CHECKPOINT_NAME, episodes=2, scenario=Scenario(max_decisions=20)
        )
    )
    assert result["preset"] == "ho2018" and result["summary"]["episodes"] == 2
    assert result["summary"]["decisions"]["mean"] == 20


def test_a_checkpoint_on_another_preset_is_refused_naming_both(ho_run, tmp_path):
    with pytest.raises(UsageError, match=r"preset min2018 .*trained on preset ho2018"):
        evaluate(
            EvalConfig(
                checkpoint=ho_run / CHECKPOINT_NAME, episodes=1, scenario=Scenario(preset="min2018")
            )
        )
    min_dir = tmp_path / "min"
    train(
        TrainConfig(
            inputs="lidar",
            num_envs=1,
            total_steps=40,
            run_dir=min_dir,
            progress=False,
            dqn=DQNConfig(learning_starts=16, replay_size=200),
            scenario=Scenario(set=("episode.max_decisions=20",)),
        )
    )
    with pytest.raises(UsageError, match=r"preset ho2018 .*trained on preset min2018"):
        evaluate(
            EvalConfig(
                checkpoint=min_dir / CHECKPOINT_NAME, episodes=1, scenario=Scenario(preset="ho2018")
            )
        )


def test_a_grid_of_another_size_is_refused_naming_both(ho_run):
    with pytest.raises(UsageError, match=r"'grid' of preset ho2018 .*built for"):
        evaluate(
            EvalConfig(
                checkpoint=ho_run / CHECKPOINT_NAME,
                episodes=1,
                scenario=Scenario(set=("grid.cells=30",)),
            )
        )


def test_the_baseline_network_and_min_s_network_on_grid_are_choices():
    config = TrainConfig.for_preset("ho2018")
    assert config.algo == "dqn" and config.inputs == "grid"
    assert TrainConfig.for_preset("min2018") == TrainConfig()
    with pytest.raises(ValueError, match="network baseline or proposed"):
        train(
            replace(config, total_steps=8, dqn=replace(config.dqn, network="multimodal")),
        )


def test_each_departure_of_his_loop_is_turned_back_by_its_flag():
    preset = ["--preset", "ho2018"]
    dqn = train_command.parse(preset).dqn
    assert dqn.store_applied and not dqn.bootstrap_time_limit and dqn.init == "truncated-normal"
    back = train_command.parse(
        [*preset, "--no-store-applied", "--bootstrap-time-limit", "--init", "torch"]
    )
    assert not back.dqn.store_applied and back.dqn.bootstrap_time_limit
    assert back.dqn.init == "torch"
    # The simulator's: the action applied as chosen.
    chosen = train_command.parse([*preset, "--set", "ego.applied_as_driven=false"])
    overrides = parse_overrides(chosen.scenario.set)
    assert not make_config("ho2018", overrides).ego.applied_as_driven


def test_the_preset_is_read_from_the_command_line():
    assert preset_in(["--algo", "dqn", "--preset", "ho2018"]) == "ho2018"
    assert preset_in(["--preset=ho2018"]) == "ho2018"
    assert preset_in([]) == "min2018"


def test_an_experiment_directory_from_before_a_trainer_setting_existed_still_resumes(tmp_path):
    plan = replace(make_plan(ExperimentConfig(experiment="min2018-table3")), out=tmp_path)
    check_directory(plan)
    record = json.loads((tmp_path / "experiment.json").read_text())
    # As the directory of a run recorded before the network, optimiser and loss settings.
    for run in record["runs"].values():
        for name in ("network", "optimizer", "loss", "rmsprop_alpha"):
            del run["dqn"][name]
    (tmp_path / "experiment.json").write_text(json.dumps(record))
    check_directory(plan)  # the new settings at their defaults: the same training
    # A setting it lacks, now at another value than its default, is a difference.
    record = json.loads((tmp_path / "experiment.json").read_text())
    del record["runs"]["dqn-both-seed0"]["dqn"]["loss"]
    (tmp_path / "experiment.json").write_text(json.dumps(record))
    changed = replace(plan.runs[0].train, dqn=replace(plan.runs[0].train.dqn, loss="mse"))
    runs = (replace(plan.runs[0], train=changed), *plan.runs[1:])
    with pytest.raises(UsageError, match=r"dqn.loss None then, 'mse' now"):
        check_directory(replace(plan, runs=runs))
    assert training_identity(changed)["dqn"]["loss"] == "mse"
