"""Rainbow's two options of the one learner: n-step returns and prioritized replay (a sum tree),
checked against hand-computed figures; and the learner, trainer and checkpoints with them."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from overtake.trainers.learning.replay_memory import FrameShapes, ReplayMemory
from overtake.trainers.learning.sum_tree import SumTree
from overtake.trainers.run.checkpoint import CHECKPOINT_NAME, load_checkpoint
from overtake.trainers.train import TrainConfig
from overtake.trainers.train import main as train

from tests.support.tiny_learning import PickTheFreeLane, greedy_score, tiny_dqn

torch.set_num_threads(1)

SHAPES = FrameShapes({"lidar": ((2,), np.dtype(np.float32))}, actions=5)
ALL = np.ones((1, 5), np.int8)


def test_the_sum_tree_draws_each_leaf_in_proportion_to_its_priority():
    tree = SumTree(6)
    priorities = np.array([1.0, 2.0, 3.0, 4.0, 0.0, 10.0])
    tree.update(np.arange(6), priorities)
    assert tree.total == pytest.approx(20.0)
    draws = tree.sample(200_000, np.random.default_rng(0))
    share = np.bincount(draws, minlength=6) / draws.size
    # Within 4 standard errors of p / total (binomial), and never the empty leaf.
    expected = priorities / priorities.sum()
    spread = np.sqrt(expected * (1 - expected) / draws.size)
    assert np.all(np.abs(share - expected) <= 4 * spread + 1e-12), share
    assert share[4] == 0.0
    # A new priority moves the draw with it.
    tree.update(np.array([5, 0]), np.array([0.0, 17.0]))
    draws = tree.sample(50_000, np.random.default_rng(1))
    assert tree.total == pytest.approx(26.0) and not np.any(draws == 5)
    assert abs(np.mean(draws == 0) - 17 / 26) < 0.01


def play(replay: ReplayMemory, episodes: list[tuple[int, bool]]) -> None:
    """One environment's episodes (length, terminated?) in turn; the frame of step s of
    episode e is (e, s), the reward of the transition into step s is s; the last episode may be
    under way (not ended: its last transition is the newest)."""
    env = np.array([0])
    for e, (length, terminated) in enumerate(episodes):
        replay.start(env, {"lidar": np.array([[e, 0]], np.float32)}, ALL)
        for s in range(1, length + 1):
            replay.add(
                env,
                np.array([s % 5]),
                np.array([float(s)]),
                np.array([terminated and s == length]),
                {"lidar": np.array([[e, s]], np.float32)},
                ALL,
            )


def test_n_step_returns_stop_at_terminations_time_limits_and_the_newest_frame():
    gamma, n = 0.5, 3
    # A terminated episode of 5, one cut by its time limit after 2, one under way at 4.
    episodes = [(5, True), (2, False), (4, False)]
    replay = ReplayMemory(100, 1, SHAPES, 2, ("lidar",), seed=0, n_step=n, gamma=gamma)
    play(replay, episodes)
    batch = replay.sample(400)
    seen = set()
    for i in range(400):
        e, s = (int(v) for v in batch.obs["lidar"][i, -1])
        length, terminated = episodes[e]
        m = min(n, length - s)  # the window stops at the episode's last transition
        expected = sum(gamma**k * (s + k + 1) for k in range(m))
        assert batch.steps[i] == m
        assert batch.reward[i] == pytest.approx(expected)
        assert bool(batch.terminated[i]) == (terminated and s + m == length)
        # The next state is the one m steps on, in the same episode.
        assert batch.next_obs["lidar"][i, -1].tolist() == [e, s + m]
        seen.add((e, s))
    # Every transition was drawn: the windows at each kind of end were all checked.
    assert seen == {(e, s) for e, (length, _) in enumerate(episodes) for s in range(length)}


def test_one_step_returns_are_the_replay_of_before():
    one = ReplayMemory(100, 1, SHAPES, 2, ("lidar",), seed=4)
    play(one, [(6, True), (3, False)])
    batch = one.sample(50)
    assert (batch.steps == 1).all()
    assert (batch.reward == batch.obs["lidar"][:, -1, 1] + 1).all()
    assert batch.weight is None and batch.leaves is None


def test_prioritized_replay_draws_by_priority_and_weighs_by_importance():
    replay = ReplayMemory(100, 1, SHAPES, 2, ("lidar",), seed=1, prioritized=True)
    play(replay, [(10, True)])
    # New transitions come in at the largest priority so far: all alike at first.
    first = replay.sample(2000, beta=1.0)
    assert first.weight is not None and np.allclose(first.weight, 1.0)
    # Transition 3 (from step 3) gets a large TD error, the others a small one.
    leaves = np.arange(10)
    error = np.where(leaves == 3, 10.0, 0.1)
    replay.update_priorities(leaves, error)
    batch = replay.sample(5000, beta=1.0)
    step = batch.obs["lidar"][:, -1, 1].astype(int)
    p = (error + replay.priority_eps) ** replay.priority_alpha
    assert abs(np.mean(step == 3) - p[3] / p.sum()) < 0.02
    # Importance weights undo the skew: (N P)^-beta over the batch's largest.
    assert batch.weight[step == 3].max() < batch.weight[step != 3].min()
    assert batch.weight.max() == pytest.approx(1.0)
    # A transition overwritten since it was drawn keeps its 0.
    assert replay.tree is not None
    replay.tree.update(np.array([5]), np.array([0.0]))
    replay.update_priorities(np.array([5]), np.array([3.0]))
    assert replay.tree.priorities[5] == 0.0


def run_config(tmp_path, **changes) -> TrainConfig:
    return TrainConfig(
        algo="dueling",
        inputs="lidar",
        num_envs=4,
        total_steps=2400,
        seed=0,
        run_dir=tmp_path / "run",
        progress=False,
        log_every=400,
        checkpoint_every=10_000,
        dqn=tiny_dqn(**changes),
    )


@pytest.mark.slow  # 2,400 steps of learning (8.5 s); the options' resume is checked below
def test_the_learner_with_n_step_returns_and_prioritized_replay_beats_random(tmp_path):
    config = run_config(tmp_path, n_step=3, prioritized=True)
    summary = train(config, envs=PickTheFreeLane(4, seed=0))
    assert summary["steps"] == 2400 and summary["updates"] > 1500
    score = greedy_score(tmp_path / "run" / CHECKPOINT_NAME)
    assert score > 0.6, f"greedy policy scored {score:.2f} a decision; random scores 0.2"


def test_a_checkpoint_carries_the_options_and_a_resume_restores_the_priorities(tmp_path):
    config = dataclasses.replace(run_config(tmp_path, n_step=3, prioritized=True), total_steps=600)
    train(config, envs=PickTheFreeLane(4, seed=0))
    checkpoint = load_checkpoint(tmp_path / "run" / CHECKPOINT_NAME)
    assert checkpoint.dqn.n_step == 3 and checkpoint.dqn.prioritized
    nodes = checkpoint.resume["replay"]["tree_nodes"].numpy()
    priorities = nodes[len(nodes) // 2 :]
    # Updated priorities differ from the largest, which new transitions got.
    assert len(np.unique(priorities[priorities > 0])) > 10
    resumed = train(
        dataclasses.replace(config, total_steps=800, resume=True),
        envs=PickTheFreeLane(4, seed=1),
    )
    assert resumed["resumed_at_step"] == 600 and resumed["steps"] == 800
    # A replay kept without priorities cannot feed a prioritized run.
    plain = ReplayMemory(100, 1, SHAPES, 2, ("lidar",), directory=tmp_path / "plain", spare=4)
    play(plain, [(5, True)])
    state = plain.mark()
    prioritized = ReplayMemory(
        100,
        1,
        SHAPES,
        2,
        ("lidar",),
        prioritized=True,
        directory=tmp_path / "plain",
        spare=4,
        reopen=True,
    )
    with pytest.raises(ValueError, match="not prioritized"):
        prioritized.load_state(state)


def test_the_update_discounts_by_the_windows_steps_and_weighs_by_importance():
    from overtake.trainers.learning.learner import ALGOS, DQNConfig, DQNLearner

    from tests.support.tiny_learning import random_obs, reward_three_for_action_two, small_shape

    shape = small_shape()
    config = DQNConfig(lstm_cells=8, hidden_units=16, learning_rate=0.01, gamma=0.9)
    obs = random_obs(shape, 32, np.random.default_rng(2))
    batch = reward_three_for_action_two(obs)

    def loss(**extra) -> tuple[float, DQNLearner]:
        torch.manual_seed(0)
        learner = DQNLearner(shape, "lidar", config, ALGOS["dqn"])
        return learner.update(batch._replace(**extra))["loss"], learner

    one, _ = loss()
    assert loss(steps=np.ones(32, dtype=np.int64))[0] == one  # 1 step: the one-step target
    three, _ = loss(steps=np.full(32, 3, dtype=np.int64))  # gamma ** 3 on the bootstrap
    assert three != one
    # Importance weights of 0 leave the loss at 0 and the network where it was; the update
    # returns every sample's TD error for its new priority.
    zero, learner = loss(weight=np.zeros(32, np.float32))
    torch.manual_seed(0)
    untouched = DQNLearner(shape, "lidar", config, ALGOS["dqn"])
    assert zero == 0.0
    assert np.allclose(learner.q_values(obs), untouched.q_values(obs))
    stats = learner.update(batch._replace(weight=np.ones(32, np.float32)))
    assert stats["td_error"].shape == (32,) and (stats["td_error"] >= 0).all()
