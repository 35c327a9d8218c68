"""A stopped run resumes exactly: stopped, or killed between checkpoints, and resumed from its
last checkpoint, a run ends with the weights of the run never stopped, bit for bit (on the
CPU, in process: the checkpoint holds the replay's account of its files, every generator, the
optimiser, the schedule, the frame stacks and the arenas' own state)."""

from __future__ import annotations

import json
import threading
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from overtake.client.episodes.scenario import Scenario, Where
from overtake.trainers.learning.learner import DQNConfig
from overtake.trainers.run.checkpoint import CHECKPOINT_NAME, load_checkpoint
from overtake.trainers.train import TrainConfig
from overtake.trainers.train import main as train


class StopAfter(threading.Event):
    """A stop that the run finds set after ``iterations`` of its loop (what SIGTERM does,
    at a step known in advance)."""

    def __init__(self, iterations: int) -> None:
        super().__init__()
        self.left = iterations

    def is_set(self) -> bool:
        self.left -= 1
        return self.left < 0 or super().is_set()


class Killed(Exception):
    """Stands for SIGKILL: the run ends where it is, with no checkpoint."""


def ddqn_run(run_dir: Path, **changes) -> TrainConfig:
    """The issue's run: Double DQN on the LIDAR, seed 3, learning from step 100, a
    checkpoint every 200 steps; short episodes, so that resets fall inside the stretches."""
    config = TrainConfig(
        algo="ddqn",
        inputs="lidar",
        num_envs=1,
        total_steps=600,
        seed=3,
        run_dir=run_dir,
        progress=False,
        log_every=50,
        checkpoint_every=200,
        dqn=DQNConfig(
            learning_starts=100,
            replay_size=1_000,
            target_update_steps=150,
            epsilon_decay_steps=400,
            train_every=1,
            lstm_cells=16,
            hidden_units=32,
        ),
        scenario=Scenario(preset="min2018", set=("episode.max_decisions=70",)),
    )
    return replace(config, **changes)


def online_weights(run_dir: Path) -> dict[str, torch.Tensor]:
    return load_checkpoint(run_dir / CHECKPOINT_NAME).learner["online"]


def assert_same_weights(a: dict[str, torch.Tensor], b: dict[str, torch.Tensor]) -> None:
    assert a.keys() == b.keys()
    for name in a:
        assert torch.equal(a[name], b[name]), f"{name} differs by {(a[name] - b[name]).abs().max()}"


@pytest.fixture(scope="module")
def never_stopped(tmp_path_factory) -> Path:
    run_dir = tmp_path_factory.mktemp("never") / "run"
    summary = train(ddqn_run(run_dir))
    assert summary["steps"] == 600 and summary["updates"] > 400
    return run_dir


def test_a_run_stopped_at_300_and_resumed_to_600_ends_with_the_same_weights(
    tmp_path, never_stopped
):
    run_dir = tmp_path / "run"
    first = train(ddqn_run(run_dir), stop=StopAfter(300))
    assert first["stopped"] and first["steps"] < 600
    assert load_checkpoint(run_dir / CHECKPOINT_NAME).step == first["steps"]
    resumed = train(ddqn_run(run_dir, resume=True))
    assert resumed["steps"] == 600 and resumed["resumed_at_step"] == first["steps"]
    assert_same_weights(online_weights(run_dir), online_weights(never_stopped))
    # The same episodes too: every episode's metrics as the run never stopped logged them.
    assert episodes(run_dir) == episodes(never_stopped)
    life = json.loads((run_dir / "run-resume-1.json").read_text())["life"]
    assert (life["replay_restored"], life["arenas_restored"], life["refill_steps"]) == (
        True,
        True,
        0,
    )


def test_a_kill_between_checkpoints_loses_only_the_steps_since_the_last(
    tmp_path, never_stopped, monkeypatch
):
    """Killed at step 350, the replay's files written on past its last checkpoint (at 200 by
    the schedule, or later where the replay's spare slots asked for one: its ring of 1,000
    transitions has 100): resumed, it trains from that checkpoint and ends where the run never
    stopped ends."""
    run_dir = tmp_path / "run"
    from overtake.trainers.run import lone_loop

    learn = lone_loop.LoneLoop.learn

    def learn_then_die(self):
        learn(self)
        if self.run_books.step >= 350:
            raise Killed

    monkeypatch.setattr(lone_loop.LoneLoop, "learn", learn_then_die)
    with pytest.raises(Killed):
        train(ddqn_run(run_dir))
    monkeypatch.setattr(lone_loop.LoneLoop, "learn", learn)
    last = load_checkpoint(run_dir / CHECKPOINT_NAME).step
    assert 200 <= last < 350
    resumed = train(ddqn_run(run_dir, resume=True))
    assert resumed["resumed_at_step"] == last and resumed["steps"] == 600
    assert_same_weights(online_weights(run_dir), online_weights(never_stopped))


def test_without_its_replay_files_a_resume_refills_and_says_so(tmp_path):
    run_dir = tmp_path / "run"
    train(ddqn_run(run_dir, total_steps=200))
    for file in (run_dir / "replay").iterdir():
        file.unlink()
    (run_dir / "replay").rmdir()
    train(ddqn_run(run_dir, total_steps=260, resume=True))
    life = json.loads((run_dir / "run-resume-1.json").read_text())["life"]
    assert life["replay_restored"] is False and life["refill_steps"] == 100
    # The episodes under way were still put back: they do not depend on the replay.
    assert life["arenas_restored"] is True


def episodes(run_dir: Path) -> list[dict]:
    """The episode lines of a run's metrics log, each once (a resumed life may log again
    what a killed life logged after the checkpoint it resumed from), without the clock."""
    seen: dict[int, dict] = {}
    for line in (run_dir / "metrics.jsonl").read_text().splitlines():
        record = json.loads(line)
        if record["kind"] == "episode":
            record.pop("wall_s")
            seen[record["episode"]] = record
    return [seen[k] for k in sorted(seen)]


def test_the_replay_files_keep_a_checkpoints_window_through_the_writes_after_it(tmp_path):
    """The replay alone: written past a checkpoint (fewer writes than its spare slots), then
    put back to the checkpoint's account, it samples exactly what it sampled then."""
    from overtake.trainers.learning.replay_memory import FrameShapes, ReplayMemory

    shapes = FrameShapes({"lidar": ((3,), np.dtype(np.float32))}, actions=5)

    def frame(value: float) -> dict[str, np.ndarray]:
        return {"lidar": np.full((2, 3), value, np.float32)}

    mask = np.ones((2, 5), np.int8)
    envs = np.arange(2)
    replay = ReplayMemory(40, 2, shapes, 2, ("lidar",), seed=1, directory=tmp_path / "r", spare=6)
    replay.start(envs, frame(0), mask)
    for t in range(1, 45):  # the rings (20 frames each) are full and have turned
        replay.add(envs, np.full(2, t % 5), np.full(2, t), np.zeros(2, bool), frame(t), mask)
    state = replay.mark()
    expected = replay.sample(16)
    assert not replay.needs_checkpoint
    for t in range(45, 51):  # six writes: every spare slot
        replay.add(envs, np.full(2, 0), np.full(2, -t), np.zeros(2, bool), frame(-t), mask)
    assert replay.needs_checkpoint
    reopened = ReplayMemory(
        40, 2, shapes, 2, ("lidar",), seed=7, directory=tmp_path / "r", spare=6, reopen=True
    )
    reopened.load_state(state)
    again = reopened.sample(16)
    for a, b in zip(expected, again, strict=True):
        if isinstance(a, dict):
            for key in a:
                np.testing.assert_array_equal(a[key], b[key])
        elif a is not None:
            np.testing.assert_array_equal(a, b)
    assert len(reopened) == state["held"] == 38


@pytest.mark.timeout(240)
def test_a_remote_run_stopped_and_resumed_ends_as_the_remote_run_never_stopped(
    tmp_path, start_server
):
    """Over the wire (protocol 1.8): the checkpoint holds the server's kept state of the
    arenas, the resumed run opens new arenas and has the server put that state into them."""
    server = start_server("resume-remote")
    # A third of the in-process run's length (the wire makes each step dearer): stopped while
    # learning (from step 100), resumed, learning on through episode ends (70 decisions).
    short = {
        "where": Where(connect=(server.endpoint,)),
        "total_steps": 200,
        "checkpoint_every": 100,
    }
    never = tmp_path / "never"
    train(ddqn_run(never, **short))
    run_dir = tmp_path / "run"
    first = train(ddqn_run(run_dir, **short), stop=StopAfter(130))
    assert first["stopped"] and 100 < first["steps"] < 200
    resumed = train(ddqn_run(run_dir, resume=True, **short))
    assert resumed["steps"] == 200 and resumed["resumed_at_step"] == first["steps"]
    assert_same_weights(online_weights(run_dir), online_weights(never))
    assert episodes(run_dir) == episodes(never)
    life = json.loads((run_dir / "run-resume-1.json").read_text())["life"]
    assert (life["replay_restored"], life["arenas_restored"]) == (True, True)
