"""The replay memory and frame stacking: stacks rebuilt within episodes as the stacker builds
them, episode ends, the ring, each frame stored once, and a replay on disk reopened.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from overtake.trainers.learning.replay_memory import FrameShapes, FrameStacker, ReplayMemory

torch.set_num_threads(1)


SHAPES = FrameShapes(
    {"lidar": ((3,), np.dtype(np.float32)), "ego": ((2,), np.dtype(np.float32))}, actions=5
)


def frame(env: int, episode: int, step: int) -> dict[str, np.ndarray]:
    """A frame that names itself: lidar = (env, episode, step)."""
    return {
        "lidar": np.array([[env, episode, step]], dtype=np.float32),
        "ego": np.array([[episode, step]], dtype=np.float32),
    }


def fill(
    replay: ReplayMemory,
    stacker: FrameStacker | None,
    lengths: dict[int, list[int]],
    terminate: bool = True,
) -> dict[tuple[int, int, int], np.ndarray]:
    """Play episodes of the given lengths per env, interleaved; returns the stacker's lidar
    stack at each (env, episode, step)."""
    stacks = {}
    for env, episode_lengths in lengths.items():
        for episode, length in enumerate(episode_lengths):
            e = np.array([env])
            first = frame(env, episode, 0)
            replay.start(e, first, np.ones((1, 5), np.int8))
            if stacker is not None:
                stacker.reset(e, first)
                stacks[(env, episode, 0)] = stacker.frames["lidar"][env].copy()
            for step in range(1, length + 1):
                nxt = frame(env, episode, step)
                ended = terminate and step == length
                replay.add(
                    e,
                    np.array([step % 5]),
                    np.array([float(step)]),
                    np.array([ended]),
                    nxt,
                    np.ones((1, 5), np.int8),
                )
                if stacker is not None:
                    stacker.push(e, nxt)
                    stacks[(env, episode, step)] = stacker.frames["lidar"][env].copy()
    return stacks


def test_replay_rebuilds_stacks_within_episodes_and_matches_the_stacker():
    replay = ReplayMemory(400, 2, SHAPES, 4, ("lidar",), seed=0)
    stacker = FrameStacker(2, SHAPES, 4, ("lidar",))
    stacks = fill(replay, stacker, {0: [2, 7, 5], 1: [9, 1, 3]})
    assert len(replay) == 2 + 7 + 5 + 9 + 1 + 3
    batch = replay.sample(500)
    for i in range(500):
        now, nxt = batch.obs["lidar"][i], batch.next_obs["lidar"][i]
        env, episode, step = (int(v) for v in now[-1])
        # Every frame of a stack is of the same env and episode; before the episode's start
        # the first frame repeats.
        assert (now[:, 0] == env).all() and (now[:, 1] == episode).all()
        assert now[:, 2].tolist() == [max(step - k, 0) for k in (3, 2, 1, 0)]
        assert nxt[:, 2].tolist() == [max(step + 1 - k, 0) for k in (3, 2, 1, 0)]
        assert (nxt[:, :2] == now[:, :2]).all()  # never across a boundary
        assert np.array_equal(now, stacks[(env, episode, step)])
        assert np.array_equal(nxt, stacks[(env, episode, step + 1)])
        assert batch.action[i] == (step + 1) % 5 and batch.reward[i] == step + 1
        assert batch.obs["ego"][i].tolist() == [episode, step]  # unstacked: the latest
        assert batch.next_obs["ego"][i].tolist() == [episode, step + 1]
        length = {0: [2, 7, 5], 1: [9, 1, 3]}[env][episode]
        assert batch.terminated[i] == (step + 1 == length)


def test_truncated_episode_ends_are_not_terminal_and_never_followed_across():
    replay = ReplayMemory(100, 1, SHAPES, 4, ("lidar",), seed=1)
    fill(replay, None, {0: [3, 3]}, terminate=False)
    batch = replay.sample(200)
    assert not batch.terminated.any()
    assert (batch.next_obs["lidar"][:, -1, 1] == batch.obs["lidar"][:, -1, 1]).all()


def test_replay_ring_never_samples_overwritten_frames():
    replay = ReplayMemory(12, 1, SHAPES, 4, ("lidar",), seed=2)
    fill(replay, None, {0: [30]})  # 31 frames through a ring of 12
    batch = replay.sample(300)
    steps = batch.obs["lidar"][:, :, 2]
    # The ring holds steps 19..30; a stack needs its 3 predecessors, the transition its next.
    assert steps.min() >= 19 and batch.next_obs["lidar"][:, -1, 2].max() <= 30
    assert (np.diff(steps, axis=1) == 1).all()
    assert set(batch.obs["lidar"][:, -1, 2].astype(int).tolist()) == set(range(22, 30))


def test_replay_refuses_to_sample_when_empty_and_to_add_before_start():
    replay = ReplayMemory(50, 1, SHAPES, 4, ("lidar",))
    with pytest.raises(RuntimeError, match="no transitions"):
        replay.sample(1)
    with pytest.raises(RuntimeError, match="before start"):
        replay.add(
            np.array([0]),
            np.array([0]),
            np.array([0.0]),
            np.array([False]),
            frame(0, 0, 1),
            np.ones((1, 5), np.int8),
        )


def test_replay_of_paper_size_stores_each_frame_once():
    shapes = FrameShapes(
        {
            "camera": ((84, 84), np.dtype(np.uint8)),
            "lidar": ((360,), np.dtype(np.float32)),
            "ego": ((6,), np.dtype(np.float32)),
        },
        actions=5,
    )
    replay = ReplayMemory(100_000, 4, shapes, 4, ("camera", "lidar"))
    # 100,000 frames of 8,520 bytes plus per-transition fields; a naive replay keeps two stacks
    # of four frames per transition.
    assert replay.nbytes < 0.9e9
    assert replay.naive_nbytes() > 7 * replay.nbytes


def test_a_replay_on_disk_reopens_as_its_state_left_it(tmp_path):
    replay = ReplayMemory(60, 2, SHAPES, 4, ("lidar",), seed=3, directory=tmp_path / "r", spare=8)
    fill(replay, None, {0: [5, 6], 1: [4]})
    state = replay.mark()
    assert not (tmp_path / "r.tmp").exists()
    other = ReplayMemory(
        60, 2, SHAPES, 4, ("lidar",), seed=9, directory=tmp_path / "r", spare=8, reopen=True
    )
    other.load_state(state)
    assert len(other) == len(replay)
    a, b = replay.sample(50), other.sample(50)
    for part, again in zip(a, b, strict=True):
        if isinstance(part, dict):
            assert part.keys() == again.keys()
            assert all(np.array_equal(part[k], again[k]) for k in part)
        else:
            assert (part is None and again is None) or np.array_equal(part, again)
    with pytest.raises(ValueError, match="same replay size"):
        ReplayMemory(80, 2, SHAPES, 4, ("lidar",), directory=tmp_path / "r", spare=8, reopen=True)
    with pytest.raises(ValueError, match="this run's"):
        ReplayMemory(
            60, 2, SHAPES, 4, ("lidar",), directory=tmp_path / "r", spare=8, reopen=True
        ).load_state({**state, "layout": {**state["layout"], "capacity": 61}})
