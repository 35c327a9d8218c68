"""Checkpoints and resume: a checkpoint's round trip, resuming a run (or starting one where
there is none), what each life of a run restored, broken or missing checkpoints, and a kill
mid-write.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from overtake.cli import UsageError
from overtake.trainers.evaluate import COMMAND as evaluate_command
from overtake.trainers.learning.learner import ALGOS, DQNConfig, DQNLearner
from overtake.trainers.run.checkpoint import CHECKPOINT_NAME, CheckpointError, load_checkpoint
from overtake.trainers.train import COMMAND as train_command
from overtake.trainers.train import TrainConfig
from overtake.trainers.train import main as train

from tests.support.tiny_learning import PickTheFreeLane, small_shape, tiny_dqn

torch.set_num_threads(1)


def test_checkpoint_round_trip_and_resume_continue_the_step_count(tmp_path):
    run_dir = tmp_path / "run"
    config = TrainConfig(
        algo="dueling",
        inputs="lidar",
        num_envs=2,
        total_steps=300,
        seed=4,
        run_dir=run_dir,
        progress=False,
        log_every=100,
        checkpoint_every=10_000,
        dqn=tiny_dqn(learning_starts=50),
    )
    first = train(config, envs=PickTheFreeLane(2, seed=1))
    checkpoint = load_checkpoint(run_dir / CHECKPOINT_NAME)
    assert (checkpoint.algo, checkpoint.inputs, checkpoint.step) == ("dueling", "lidar", 300)
    assert checkpoint.space["lidar"]["shape"] == [5] and checkpoint.net_shape.lidar_rays == 5
    assert checkpoint.episodes == first["episodes"] and checkpoint.dqn == config.dqn
    # The learner comes back exactly: same Q-values.
    obs = {
        "lidar": np.random.default_rng(0).uniform(0, 80, (3, 4, 5)).astype(np.float32),
        "ego": np.zeros((3, 6), np.float32),
    }
    restored = checkpoint.make_learner()
    assert restored.algo == ALGOS["dueling"] and restored.double
    assert restored.updates == first["updates"]

    # Running again without --resume refuses to overwrite the run.
    with pytest.raises(UsageError, match="--resume"):
        train(config, envs=PickTheFreeLane(2, seed=1))
    # Resumed in mixed precision: the weights are float32 either way.
    resumed = train(
        replace(config, total_steps=500, resume=True, precision="bf16"),
        envs=PickTheFreeLane(2, seed=2),
    )
    assert resumed["steps"] == 500 and resumed["updates"] > first["updates"]
    after = load_checkpoint(run_dir / CHECKPOINT_NAME)
    assert after.step == 500 and after.resumes == 1
    assert not np.allclose(after.make_learner().q_values(obs), restored.q_values(obs))
    assert (run_dir / "run.json").exists() and (run_dir / "run-resume-1.json").exists()
    steps = [
        json.loads(line)["step"]
        for line in (run_dir / "metrics.jsonl").read_text().splitlines()
        if json.loads(line)["kind"] == "train"
    ]
    assert steps == sorted(steps) and steps[-1] >= 400 and any(s <= 300 for s in steps)
    with pytest.raises(CheckpointError, match="algo=dueling"):
        train(
            replace(config, algo="dqn", total_steps=600, resume=True),
            envs=PickTheFreeLane(2, seed=2),
        )


def resumable(run_dir: Path, **changes: Any) -> TrainConfig:
    """A short run that continues from its checkpoint when started again."""
    config = TrainConfig(
        inputs="lidar",
        num_envs=1,
        total_steps=100,
        seed=3,
        run_dir=run_dir,
        progress=False,
        log_every=50,
        resume_if_found=True,
        dqn=tiny_dqn(learning_starts=20),
    )
    return replace(config, **changes)


def test_resume_if_found_continues_a_run_and_starts_one_where_there_is_none(tmp_path):
    """What a restarted compose trainer does: same command, same --run-dir."""
    run_dir = tmp_path / "run"
    config = resumable(run_dir)
    # No checkpoint yet: a fresh run, not a refusal.
    first = train(config, envs=PickTheFreeLane(1, seed=1))
    assert first["steps"] == 100
    assert load_checkpoint(run_dir / CHECKPOINT_NAME).resumes == 0
    assert not (run_dir / "run-resume-1.json").exists()
    # The same command again, asked for more steps: it continues that run.
    resumed = train(replace(config, total_steps=160), envs=PickTheFreeLane(1, seed=2))
    assert resumed["steps"] == 160 and resumed["updates"] > first["updates"]
    after = load_checkpoint(run_dir / CHECKPOINT_NAME)
    assert after.step == 160 and after.resumes == 1
    assert (run_dir / "run-resume-1.json").exists()
    # Like --resume, it refuses a checkpoint of another algorithm.
    with pytest.raises(CheckpointError, match="algo=dueling"):
        train(replace(config, algo="dqn", total_steps=200), envs=PickTheFreeLane(1))


def test_each_life_of_a_run_says_what_it_restored_and_a_bare_network_resumes(tmp_path):
    """A run's provenance: each life's run record says from which step it learned, on which
    device, and what of the checkpoint it restored. A checkpoint carrying the online network
    alone (brought back from another machine without the optimiser's moments) resumes with
    the target network copied from it and a fresh optimiser, and says so."""
    run_dir = tmp_path / "run"
    config = resumable(run_dir, replay_on_disk=False)
    train(config, envs=PickTheFreeLane(1, seed=1))
    first = json.loads((run_dir / "run.json").read_text())["life"]
    assert first == {
        "from_step": 0,
        "members": 1,  # a lone run (members of one learner say how many they were)
        "device": "cpu",
        "precision": "fp32",
        "target_restored": None,
        "optimizer_restored": None,
        "replay_restored": None,
        "refill_steps": None,
        "arenas_restored": None,
    }
    # Strip the checkpoint to its online network, as a transfer from a GPU machine did.
    payload = torch.load(run_dir / CHECKPOINT_NAME, weights_only=True)
    online = payload["learner"]["online"]
    payload["learner"] = {"online": online, "updates": payload["learner"]["updates"]}
    torch.save(payload, run_dir / CHECKPOINT_NAME)
    train(replace(config, total_steps=140), envs=PickTheFreeLane(1, seed=2))
    life = json.loads((run_dir / "run-resume-1.json").read_text())["life"]
    assert life["from_step"] == 100 and life["device"] == "cpu"
    assert (life["target_restored"], life["optimizer_restored"], life["replay_restored"]) == (
        False,
        False,
        False,
    )
    assert life["refill_steps"] == max(
        20, config.dqn.batch_size
    )  # learning_starts, a batch at least
    learner = load_checkpoint(run_dir / CHECKPOINT_NAME).make_learner()
    assert learner.updates > 0
    # A whole checkpoint restores everything but the replay (kept in memory only in this run)
    # and the episodes under way (a foreign environment's, which cannot be restored).
    train(replace(config, total_steps=160), envs=PickTheFreeLane(1, seed=3))
    whole = json.loads((run_dir / "run-resume-2.json").read_text())["life"]
    assert (whole["target_restored"], whole["optimizer_restored"]) == (True, True)
    assert (whole["replay_restored"], whole["arenas_restored"]) == (False, False)


def test_a_bare_network_restores_its_target_as_a_copy_of_it():
    shape, config = small_shape(), DQNConfig(lstm_cells=8, hidden_units=16)
    learner = DQNLearner(shape, "lidar", config, ALGOS["ddqn"])
    other = DQNLearner(shape, "lidar", config, ALGOS["ddqn"])
    restored = other.load_state_dict({"online": learner.online.state_dict()})
    assert restored == {"target": False, "optimizer": False}
    for a, b in zip(other.target.parameters(), learner.online.parameters(), strict=True):
        assert torch.equal(a, b)


def test_the_steps_after_the_last_log_line_get_a_line_of_their_own(tmp_path):
    # 130 steps logged every 50: lines at 50 and 100, and one for the last 30 steps, so a
    # curve of the reward per window keeps its last point and the windows add up to all of it.
    run_dir = tmp_path / "run"
    config = TrainConfig(
        inputs="lidar",
        num_envs=1,
        total_steps=130,
        seed=3,
        run_dir=run_dir,
        progress=False,
        log_every=50,
        dqn=tiny_dqn(learning_starts=20),
    )
    train(config, envs=PickTheFreeLane(1, seed=1))
    records = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    lines = [r for r in records if r["kind"] == "train"]
    assert [r["step"] for r in lines] == [50, 100, 130]
    assert all(r["reward_sum"] != 0 for r in lines)


def test_resume_without_a_checkpoint_and_a_broken_checkpoint_say_what_is_wrong(tmp_path):
    config = TrainConfig(
        inputs="lidar", run_dir=tmp_path / "none", resume=True, progress=False, dqn=tiny_dqn()
    )
    with pytest.raises(CheckpointError, match="no checkpoint"):
        train(config)
    broken = tmp_path / "broken.pt"
    broken.write_bytes(b"not a checkpoint at all")
    with pytest.raises(CheckpointError, match="not a checkpoint overtake-train wrote"):
        load_checkpoint(broken)
    torch.save({"header": {"format": "something-else/9"}}, tmp_path / "foreign.pt")
    with pytest.raises(CheckpointError, match="overtake-dqn/1.*something-else/9"):
        load_checkpoint(tmp_path / "foreign.pt")


def test_the_commands_print_what_is_wrong_and_exit_non_zero(tmp_path):
    """main() raises the typed error; the command prints ``<prog>: <message>`` and exits."""
    with pytest.raises(SystemExit) as exited:
        train_command.run(
            ["--total-steps", "0", "--run-dir", str(tmp_path / "run"), "--no-progress"]
        )
    assert exited.value.code == "overtake-train: --total-steps and --num-envs must be >= 1"
    assert not (tmp_path / "run").exists()
    broken = tmp_path / "broken.pt"
    broken.write_bytes(b"not a checkpoint at all")
    with pytest.raises(SystemExit) as exited:
        evaluate_command.run(["--checkpoint", str(broken)])
    assert str(exited.value.code).startswith(
        f"overtake-eval: {broken} is not a checkpoint overtake-train wrote ("
    )
    with pytest.raises(SystemExit) as exited:
        train_command.run(
            ["--precision", "fp16", "--run-dir", str(tmp_path / "run"), "--no-progress"]
        )
    assert exited.value.code == (
        "overtake-train: precision fp16 needs a CUDA device (its loss scaling is CUDA's), got "
        "device 'cpu': use bf16 there"
    )
    assert not (tmp_path / "run").exists()
    with pytest.raises(SystemExit) as exited:
        evaluate_command.run(["--policy", "rule", "--episodes", "0"])
    assert exited.value.code == "overtake-eval: --episodes must be >= 1, got 0"


def test_a_kill_mid_write_leaves_the_previous_checkpoint_whole(tmp_path, monkeypatch):
    run_dir = tmp_path / "run"
    config = TrainConfig(
        inputs="lidar",
        num_envs=1,
        total_steps=100,
        run_dir=run_dir,
        progress=False,
        dqn=tiny_dqn(learning_starts=20),
    )
    train(config, envs=PickTheFreeLane(1))
    good = (run_dir / CHECKPOINT_NAME).read_bytes()

    def dies(*_args: Any, **_kwargs: Any) -> None:
        raise KeyboardInterrupt("killed while writing")

    monkeypatch.setattr(torch, "save", dies)
    with pytest.raises(KeyboardInterrupt):
        train(replace(config, total_steps=200, resume=True), envs=PickTheFreeLane(1))
    assert (run_dir / CHECKPOINT_NAME).read_bytes() == good
    assert load_checkpoint(run_dir / CHECKPOINT_NAME).step == 100
