"""The learner, its network, the replay and the train / eval commands."""

from __future__ import annotations

import contextlib
import json
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium import spaces

from overtake.client.commands import UsageError
from overtake.trainers.checkpoint import CHECKPOINT_NAME, CheckpointError, load_checkpoint
from overtake.trainers.evaluate import COMMAND as evaluate_command
from overtake.trainers.evaluate import EvalConfig
from overtake.trainers.evaluate import main as evaluate
from overtake.trainers.heads import HeadSpec, dueling_q
from overtake.trainers.learner import ALGOS, DQNConfig, DQNLearner, execution_device
from overtake.trainers.network import NetworkShape, QNetwork
from overtake.trainers.objectives import masked, td_target
from overtake.trainers.replay_memory import FrameShapes, FrameStacker, ReplayBatch, ReplayMemory
from overtake.trainers.train import COMMAND as train_command
from overtake.trainers.train import TrainConfig
from overtake.trainers.train import main as train
from overtake.viz.recording import RecordingConfig

torch.set_num_threads(1)

# --- targets, dueling, masking -----------------------------------------------------------------


def test_dqn_target_takes_the_target_networks_max_over_allowed_actions():
    reward = torch.tensor([1.0, 0.5, 2.0])
    terminated = torch.tensor([False, True, False])
    next_q_target = torch.tensor([[1.0, 3.0, 2.0], [5.0, 0.0, 0.0], [4.0, 9.0, 1.0]])
    mask = torch.tensor([[1, 1, 1], [1, 1, 1], [1, 0, 1]], dtype=torch.int8)
    target = td_target(reward, terminated, 0.9, next_q_target, mask)
    # row 0: 1 + 0.9 * 3; row 1 terminated: 0.5; row 2: action 1 (9) is masked: 2 + 0.9 * 4
    assert torch.allclose(target, torch.tensor([1.0 + 0.9 * 3.0, 0.5, 2.0 + 0.9 * 4.0]))


def test_double_target_lets_the_online_network_choose_and_the_target_network_value():
    reward = torch.tensor([1.0, 0.0])
    terminated = torch.tensor([False, False])
    next_q_target = torch.tensor([[1.0, 3.0, 2.0], [7.0, 6.0, 5.0]])
    next_q_online = torch.tensor([[3.0, 1.0, 2.0], [0.0, 10.0, 8.0]])
    mask = torch.tensor([[1, 1, 1], [1, 0, 1]], dtype=torch.int8)
    target = td_target(reward, terminated, 0.5, next_q_target, mask, next_q_online)
    # row 0: online picks action 0, valued 1 by the target: 1 + 0.5 * 1 (DQN would take 3)
    # row 1: online's best (1) is masked, so it picks 2, valued 5: 0 + 0.5 * 5
    assert torch.allclose(target, torch.tensor([1.5, 2.5]))


def test_dueling_aggregation_subtracts_the_mean_advantage():
    value = torch.tensor([[2.0], [-1.0]])
    advantage = torch.tensor([[1.0, 2.0, 3.0], [0.0, 0.0, 6.0]])
    q = dueling_q(value, advantage)
    assert torch.allclose(q, torch.tensor([[1.0, 2.0, 3.0], [-3.0, -3.0, 3.0]]))


def small_shape(**changes: Any) -> NetworkShape:
    shape = NetworkShape(
        camera_hw=(36, 36),
        lidar_rays=8,
        ego_size=6,
        actions=5,
        stack=4,
        lidar_max_m=80.0,
        ego_high=(100.0, 22.2, 4.0, 12.0, 1.0, 1.0),
    )
    return replace(shape, **changes)


def random_obs(shape: NetworkShape, batch: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    return {
        "camera": rng.integers(0, 256, (batch, shape.stack) + shape.camera_hw, dtype=np.uint8),
        "lidar": rng.uniform(0, 80, (batch, shape.stack, shape.lidar_rays)).astype(np.float32),
        "ego": rng.uniform(0, 1, (batch, shape.ego_size)).astype(np.float32),
    }


@pytest.mark.parametrize("inputs", ["camera", "lidar", "both"])
def test_dueling_network_output_is_value_plus_centred_advantage(inputs):
    torch.manual_seed(0)
    shape = small_shape()
    net = QNetwork(shape, inputs, head=HeadSpec("dueling"), lstm_cells=16, hidden=32)
    obs = random_obs(shape, 3, np.random.default_rng(0))
    seen: dict[str, torch.Tensor] = {}
    net.head.value.register_forward_hook(lambda _m, _i, out: seen.__setitem__("v", out))
    net.head.advantage.register_forward_hook(lambda _m, _i, out: seen.__setitem__("a", out))
    q = net(
        torch.as_tensor(obs["camera"]), torch.as_tensor(obs["lidar"]), torch.as_tensor(obs["ego"])
    )
    assert q.shape == (3, 5)
    expected = seen["v"] + seen["a"] - seen["a"].mean(dim=1, keepdim=True)
    assert torch.allclose(q, expected)
    assert torch.allclose(q.mean(dim=1, keepdim=True), seen["v"], atol=1e-6)


def test_camera_only_and_lidar_only_networks_ignore_the_other_sensor():
    torch.manual_seed(0)
    shape = small_shape()
    rng = np.random.default_rng(1)
    obs = random_obs(shape, 2, rng)
    other = random_obs(shape, 2, rng)
    for inputs, changed in (("camera", "lidar"), ("lidar", "camera")):
        net = QNetwork(shape, inputs, lstm_cells=16, hidden=32)
        mixed = {**obs, changed: other[changed]}
        a = net(*(torch.as_tensor(obs[k]) for k in ("camera", "lidar", "ego")))
        b = net(*(torch.as_tensor(mixed[k]) for k in ("camera", "lidar", "ego")))
        assert torch.equal(a, b)
        c = net(
            *(
                torch.as_tensor({**obs, inputs: other[inputs]}[k])
                for k in ("camera", "lidar", "ego")
            )
        )
        assert not torch.equal(a, c)


def test_paper_network_has_the_table_ii_layers():
    shape = NetworkShape(camera_hw=(84, 84), lidar_rays=360, ego_size=6, actions=5)
    net = QNetwork(shape, "both")
    convs = [m for m in net.conv if isinstance(m, torch.nn.Conv2d)]
    assert [(c.in_channels, c.out_channels, c.kernel_size, c.stride) for c in convs] == [
        (4, 32, (8, 8), (4, 4)),
        (32, 64, (4, 4), (2, 2)),
        (64, 64, (3, 3), (1, 1)),
    ]
    assert (net.lstm.input_size, net.lstm.hidden_size) == (360, 256)
    assert net.fuse[0].in_features == 64 * 7 * 7 + 256 + 6 and net.fuse[0].out_features == 512
    assert net.head.q_layer.out_features == 5


def test_acting_never_picks_a_masked_action():
    shape = small_shape()
    learner = DQNLearner(shape, "lidar", DQNConfig(lstm_cells=8, hidden_units=16), ALGOS["ddqn"])
    rng = np.random.default_rng(0)
    obs = random_obs(shape, 64, rng)
    q = learner.q_values(obs)
    mask = np.ones((64, 5), dtype=np.int8)
    mask[np.arange(64), q.argmax(axis=1)] = 0  # the greedy choice is not allowed
    mask[:, 4] = 0
    for epsilon in (0.0, 1.0, 0.5):
        actions, _ = learner.act(obs, mask, epsilon, rng)
        assert mask[np.arange(64), actions].all()
    greedy, _ = learner.act(obs, mask, 0.0, rng)
    assert np.array_equal(greedy, np.where(mask.astype(bool), q, -np.inf).argmax(axis=1))
    explored, _ = learner.act(obs, mask, 1.0, rng)
    assert len(set(explored.tolist())) >= 3  # random among the allowed, not fixed


def test_masked_leaves_rows_with_nothing_allowed_unmasked():
    q = torch.tensor([[1.0, 2.0], [3.0, 4.0]])
    out = masked(q, torch.tensor([[0, 1], [0, 0]], dtype=torch.int8))
    assert out[0, 0] == float("-inf") and torch.equal(out[1], q[1])


def test_epsilon_falls_linearly_then_stays():
    config = DQNConfig(epsilon_start=1.0, epsilon_end=0.1, epsilon_decay_steps=100)
    assert [round(config.epsilon(s), 6) for s in (0, 50, 100, 1000)] == [1.0, 0.55, 0.1, 0.1]


def reward_three_for_action_two(obs: dict[str, np.ndarray]) -> ReplayBatch:
    """A replay batch of 32 one-step episodes: action 2 taken, reward 3, nothing after (with
    gamma 0, Q of action 2 should go to 3)."""
    return ReplayBatch(
        obs=obs,
        next_obs=obs,
        action=np.full(32, 2),
        reward=np.full(32, 3.0, dtype=np.float32),
        terminated=np.zeros(32, dtype=bool),
        steps=np.ones(32, dtype=np.int64),
        next_mask=np.ones((32, 5), np.int8),
    )


def test_update_moves_q_towards_the_target():
    torch.manual_seed(0)
    shape = small_shape()
    config = DQNConfig(lstm_cells=8, hidden_units=16, learning_rate=0.01, gamma=0.0)
    learner = DQNLearner(shape, "lidar", config, ALGOS["dqn"])
    obs = random_obs(shape, 32, np.random.default_rng(2))
    batch = reward_three_for_action_two(obs)
    before = learner.q_values(obs)[:, 2].mean()
    for _ in range(100):
        learner.update(batch)
    after = learner.q_values(obs)[:, 2].mean()
    assert abs(after - 3.0) < 0.1 < abs(before - 3.0)


def test_devices_and_precisions_this_machine_cannot_run_are_refused_saying_why():
    assert execution_device("cpu", "bf16") == torch.device("cpu")
    with pytest.raises(ValueError, match="'gpu' is not a PyTorch device name"):
        execution_device("gpu")
    with pytest.raises(ValueError, match="fp16 needs a CUDA device.*'cpu': use bf16"):
        execution_device("cpu", "fp16")
    with pytest.raises(ValueError, match="precision is one of fp32, bf16, fp16, got 'fp8'"):
        execution_device("cpu", "fp8")  # type: ignore[arg-type]
    if not torch.cuda.is_available():
        with pytest.raises(ValueError, match=r"'cuda:1' asked for, but this PyTorch .* no CUDA"):
            execution_device("cuda:1")
    else:
        count = torch.cuda.device_count()
        with pytest.raises(ValueError, match=f"has {count} CUDA device"):
            execution_device(f"cuda:{count}")


@pytest.mark.parametrize("inputs", ["lidar", "both"])
def test_bf16_runs_the_forward_passes_in_bf16_and_keeps_float32_weights(inputs):
    shape = small_shape()
    config = DQNConfig(lstm_cells=8, hidden_units=16, learning_rate=0.01, gamma=0.0)
    torch.manual_seed(0)
    full = DQNLearner(shape, inputs, config, ALGOS["ddqn"])
    mixed = DQNLearner(shape, inputs, config, ALGOS["ddqn"], precision="bf16")
    mixed.load_state_dict(full.state_dict())
    obs = random_obs(shape, 32, np.random.default_rng(3))
    q_full, q_mixed = full.q_values(obs), mixed.q_values(obs)
    assert q_mixed.dtype == np.float32
    # bf16 keeps 8 bits of mantissa: close to float32, and not the same numbers.
    assert not np.array_equal(q_full, q_mixed)
    np.testing.assert_allclose(q_mixed, q_full, atol=0.05 * np.abs(q_full).max())
    batch = reward_three_for_action_two(obs)
    before = mixed.q_values(obs)[:, 2].mean()
    for _ in range(100):
        stats = mixed.update(batch)
        assert np.isfinite(stats["loss"])
    assert all(p.dtype == torch.float32 for p in mixed.online.parameters())
    assert "grad_scaler" not in mixed.state_dict()  # loss scaling is fp16's alone
    # The Q head runs in float32 under autocast too (bf16 would tie nearby Q-values).
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert mixed.online(*mixed._tensors(obs)).dtype == torch.float32
    after = mixed.q_values(obs)[:, 2].mean()
    assert abs(after - 3.0) < 0.15 < abs(before - 3.0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="fp16 needs a CUDA device: none here")
def test_fp16_learns_with_loss_scaling_and_its_scale_survives_a_checkpoint():
    shape = small_shape()
    config = DQNConfig(lstm_cells=8, hidden_units=16, learning_rate=0.01, gamma=0.0)
    learner = DQNLearner(shape, "both", config, ALGOS["dueling"], device="cuda", precision="fp16")
    obs = random_obs(shape, 32, np.random.default_rng(3))
    batch = reward_three_for_action_two(obs)
    before = learner.q_values(obs)[:, 2].mean()
    for _ in range(100):
        assert np.isfinite(learner.update(batch)["loss"])
    assert abs(learner.q_values(obs)[:, 2].mean() - 3.0) < 0.15 < abs(before - 3.0)
    state = learner.state_dict()
    restored = DQNLearner(shape, "both", config, ALGOS["dueling"], device="cuda", precision="fp16")
    restored.load_state_dict(state)
    assert restored.scaler.get_scale() == learner.scaler.get_scale()


# --- replay and stacking -------------------------------------------------------------------------

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


# --- a purpose-built tiny environment: the learner learns ----------------------------------------


class PickTheFreeLane(gym.vector.VectorEnv):
    """Each decision the LIDAR shows five distances; driving towards the largest pays 1.

    Random scores 0.2 a decision; a policy that reads its newest scan scores 1. Episodes of
    ``length`` decisions, Gymnasium next-step autoreset, overtake's observation keys.
    """

    metadata = {"autoreset_mode": gym.vector.AutoresetMode.NEXT_STEP}  # noqa: RUF012

    def __init__(self, num_envs: int, length: int = 16, seed: int = 0) -> None:
        self.num_envs, self.length = num_envs, length
        self.single_observation_space = spaces.Dict(
            {
                "ego": spaces.Box(-1.0, 1.0, (6,), np.float32),
                "lidar": spaces.Box(0.0, 80.0, (5,), np.float32),
            }
        )
        self.single_action_space = spaces.Discrete(5)
        self.observation_space = gym.vector.utils.batch_space(
            self.single_observation_space, num_envs
        )
        self.action_space = spaces.MultiDiscrete(np.full(num_envs, 5))
        self.rng = np.random.default_rng(seed)
        self.t = np.zeros(num_envs, dtype=int)
        self.total = np.zeros(num_envs)
        self.autoreset = np.zeros(num_envs, dtype=bool)

    def _obs(self):
        self.lidar = self.rng.uniform(0.0, 80.0, (self.num_envs, 5)).astype(np.float32)
        return {"ego": np.zeros((self.num_envs, 6), np.float32), "lidar": self.lidar.copy()}

    def _info(self):
        return {"action_mask": np.ones((self.num_envs, 5), np.int8)}

    def reset(self, *, seed=None, options=None):
        self.t[:] = 0
        self.total[:] = 0
        self.autoreset[:] = False
        return self._obs(), self._info()

    def step(self, actions):
        reward = (np.asarray(actions) == self.lidar.argmax(axis=1)).astype(float)
        reward[self.autoreset] = 0.0
        self.t = np.where(self.autoreset, 0, self.t + 1)
        self.total = np.where(self.autoreset, 0.0, self.total + reward)
        truncated = self.t >= self.length
        info = self._info()
        if truncated.any():
            info["metrics"] = {
                "return": np.where(truncated, self.total, 0.0),
                "avg_speed_kmh": np.zeros(self.num_envs),
            }
            info["_metrics"] = truncated
        self.autoreset = truncated
        return self._obs(), reward, np.zeros(self.num_envs, bool), truncated, info


class WatchEnvZero(gym.vector.VectorEnv):
    """Passes everything through, keeping per step environment 0's LIDAR before the step, its
    action, its reward, and whether the step was its autoreset."""

    def __init__(self, env: gym.vector.VectorEnv) -> None:
        self.env = env
        self.metadata = env.metadata
        self.num_envs = env.num_envs
        self.single_observation_space = env.single_observation_space
        self.single_action_space = env.single_action_space
        self.observation_space, self.action_space = env.observation_space, env.action_space
        self.log: list[tuple[np.ndarray, int, float, bool]] = []
        self._last, self._resetting = None, False

    def reset(self, *, seed=None, options=None):
        obs, info = self.env.reset(seed=seed, options=options)
        self._last, self._resetting = obs["lidar"][0].copy(), False
        return obs, info

    def step(self, actions):
        obs, reward, terminated, truncated, info = self.env.step(actions)
        self.log.append((self._last, int(actions[0]), float(reward[0]), self._resetting))
        self._last = obs["lidar"][0].copy()
        self._resetting = bool(terminated[0] or truncated[0])
        return obs, reward, terminated, truncated, info


def tiny_dqn(**changes: Any) -> DQNConfig:
    settings = dict(
        learning_rate=0.002,
        batch_size=32,
        replay_size=4000,
        learning_starts=300,
        gamma=0.5,
        epsilon_decay_steps=1500,
        epsilon_end=0.05,
        target_update_steps=200,
        train_every=1,
        lstm_cells=32,
        hidden_units=64,
    )
    settings.update(changes)
    return DQNConfig(**settings)


def greedy_score(checkpoint_path: Path, episodes: int = 200) -> float:
    checkpoint = load_checkpoint(checkpoint_path)
    learner = checkpoint.make_learner()
    env = PickTheFreeLane(episodes, seed=99)
    obs, info = env.reset()
    stack = np.repeat(obs["lidar"][:, None], checkpoint.dqn.stack, axis=1)
    actions, _ = learner.act(
        {"lidar": stack, "ego": obs["ego"]}, info["action_mask"], 0.0, np.random.default_rng(0)
    )
    _, reward, *_ = env.step(actions)
    return float(reward.mean())


# bf16 is slow-marked (6 s each): fp32 learns in the default run, bf16 with -m slow.
@pytest.mark.parametrize("precision", ["fp32", pytest.param("bf16", marks=pytest.mark.slow)])
def test_learner_beats_random_on_a_tiny_environment(tmp_path, precision):
    config = TrainConfig(
        algo="ddqn",
        inputs="lidar",
        precision=precision,
        num_envs=4,
        total_steps=2400,
        seed=0,
        run_dir=tmp_path / "run",
        progress=False,
        log_every=400,
        checkpoint_every=10_000,
        dqn=tiny_dqn(),
    )
    env = PickTheFreeLane(4, seed=0)
    summary = train(config, envs=env)
    assert summary["steps"] >= 2400 and summary["updates"] > 1500
    score = greedy_score(tmp_path / "run" / CHECKPOINT_NAME)
    assert score > 0.6, f"greedy policy scored {score:.2f} a decision; random scores 0.2"


# --- checkpoints and resume ----------------------------------------------------------------------


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


# --- smoke runs on the real simulator -------------------------------------------------------------

SMOKE_DQN = dict(
    learning_starts=60, replay_size=2000, target_update_steps=100, epsilon_decay_steps=200
)


@pytest.mark.parametrize("algo", ["dqn", "ddqn", "dueling", "qr"])
def test_each_algorithm_trains_in_process_and_its_checkpoint_evaluates(tmp_path, algo):
    run_dir = tmp_path / algo
    summary = train(
        TrainConfig(
            algo=algo,
            inputs="both",
            num_envs=2,
            total_steps=240,
            run_dir=run_dir,
            progress=False,
            log_every=80,
            # A small camera, so that an update costs little (about half this test's time at
            # 80 px); the preset's own network trains in test_export.
            set=("episode.max_decisions=60", "camera.width_px=36", "camera.height_px=36"),
            dqn=DQNConfig(**SMOKE_DQN),
        )
    )
    assert summary["steps"] >= 240 and summary["updates"] >= 40 and summary["episodes"] >= 2
    records = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    episodes = [r for r in records if r["kind"] == "episode"]
    assert episodes and all(r["decisions"] == 60 or r["terminated"] for r in episodes)
    assert any(r["kind"] == "train" and r["loss"] is not None for r in records)
    run = json.loads((run_dir / "run.json").read_text())
    assert run["algo"]["name"] == algo and run["sim_config"]["episode"]["max_decisions"] == 60
    assert run["versions"]["torch"].startswith("2.13") and run["commit"]
    result = evaluate(
        EvalConfig(
            checkpoint=run_dir / CHECKPOINT_NAME,
            episodes=2,
            max_decisions=30,
            traffic="light",
            json_out=tmp_path / "eval.json",
        )
    )
    assert result["summary"]["episodes"] == 2
    assert result["summary"]["decisions"]["mean"] == 30
    assert result["overrides"]["traffic.density"] == "light"
    assert json.loads((tmp_path / "eval.json").read_text())["name"].startswith(f"{algo}/both")


@pytest.mark.parametrize("algo", ["dqn", "ddqn", "dueling", "qr"])
def test_each_algorithm_trains_against_a_real_server(tmp_path, start_server, algo):
    server = start_server(f"train-{algo}")
    summary = train(
        TrainConfig(
            algo=algo,
            inputs="lidar",
            num_envs=2,
            total_steps=200,
            connect=server.endpoint,
            run_dir=tmp_path / algo,
            progress=False,
            set=("episode.max_decisions=50",),
            dqn=DQNConfig(**SMOKE_DQN),
        )
    )
    assert summary["steps"] >= 200 and summary["updates"] >= 30 and summary["episodes"] >= 2
    run = json.loads((tmp_path / algo / "run.json").read_text())
    assert run["overrides"]["camera.enabled"] is False  # lidar-only: no camera rendered
    assert run["config"]["connect"] == server.endpoint


def test_overlapped_remote_training_is_deterministic_and_lock_step_stays(tmp_path, start_server):
    """With --overlap on the learner updates while the server simulates (one group), or with
    --overlap-parts 2 the 4 arenas are two groups stepped in turn; two runs of one seed store
    the same episodes and learn the same losses either way; --overlap off is one group again,
    stepped and then learned from."""
    server = start_server("train-overlap")

    def run(name: str, overlap: str, parts: int = 1) -> tuple[dict, list[dict]]:
        summary = train(
            TrainConfig(
                algo="ddqn",
                inputs="lidar",
                num_envs=4,
                total_steps=240,
                seed=9,
                connect=server.endpoint,
                run_dir=tmp_path / name,
                progress=False,
                overlap=overlap,
                overlap_parts=parts,
                log_every=40,
                set=("episode.max_decisions=25",),
                dqn=DQNConfig(**SMOKE_DQN),
            )
        )
        lines = [
            {
                k: v
                for k, v in json.loads(line).items()
                if k not in ("wall_s", "steps_per_s") and not k.startswith("time_")
            }
            for line in (tmp_path / name / "metrics.jsonl").read_text().splitlines()
        ]
        return summary, lines

    one, one_lines = run("one-a", overlap="on")
    assert one["parts"] == 1 and one["steps"] == 240 and one["updates"] >= 30
    # One send per vector step, plus the last one in flight when the run ended.
    assert one["env_steps_called"] >= 240 // 4 + 1
    assert run("one-b", overlap="on")[1] == one_lines
    halves, halves_lines = run("two-a", overlap="on", parts=2)
    assert halves["parts"] == 2 and halves["steps"] == 240 and halves["updates"] >= 30
    # Every send was a round of one of the two groups; two parts of 2 arenas each.
    assert halves["env_steps_called"] >= 240 // 2
    episodes = [line for line in halves_lines if line["kind"] == "episode"]
    assert len(episodes) >= 4 and {line["env"] for line in episodes} == {0, 1, 2, 3}
    again, again_lines = run("two-b", overlap="on", parts=2)
    assert again_lines == halves_lines
    assert again["updates"] == halves["updates"]
    assert halves_lines != one_lines
    lock, lock_lines = run("lock", overlap="off", parts=2)
    assert lock["parts"] == 1 and lock["steps"] == 240
    # The learner updated at other times: before the step's transitions were stored.
    assert lock_lines != one_lines and lock_lines != halves_lines


def test_baselines_evaluate_on_the_same_seeds(tmp_path):
    rule = evaluate(EvalConfig(policy="rule", episodes=2, max_decisions=40, seed=5))
    again = evaluate(EvalConfig(policy="rule", episodes=2, max_decisions=40, seed=5))
    assert rule["episodes"] == again["episodes"]
    random = evaluate(EvalConfig(policy="random", episodes=2, max_decisions=40, seed=5))
    assert random["summary"]["lane_changes"]["mean"] > rule["summary"]["lane_changes"]["mean"]
    with pytest.raises(UsageError, match="exactly one"):
        evaluate(EvalConfig(policy="rule", checkpoint=tmp_path / "x.pt"))


class CountingEnv(PickTheFreeLane):
    """Frames that name themselves (LIDAR = env, episode, step, 0, 0); episodes of random
    length end by termination or truncation, with Gymnasium's next-step autoreset."""

    def __init__(self, num_envs: int, seed: int = 0) -> None:
        super().__init__(num_envs, seed=seed)
        self.episode = np.zeros(num_envs, dtype=int)

    def _obs(self):
        lidar = np.zeros((self.num_envs, 5), np.float32)
        lidar[:, 0], lidar[:, 1], lidar[:, 2] = np.arange(self.num_envs), self.episode, self.t
        self.lidar = lidar
        return {"ego": np.zeros((self.num_envs, 6), np.float32), "lidar": lidar.copy()}

    def step(self, actions):
        resetting = self.autoreset.copy()
        self.episode = self.episode + resetting
        self.t = np.where(resetting, 0, self.t + 1)
        ended = ~resetting & (self.rng.random(self.num_envs) < 0.15)
        terminated = ended & (self.rng.random(self.num_envs) < 0.5)
        truncated = ended & ~terminated
        info = self._info()
        if ended.any():
            info["metrics"] = {
                "return": np.zeros(self.num_envs),
                "avg_speed_kmh": np.zeros(self.num_envs),
            }
            info["_metrics"] = ended
        self.autoreset = ended
        return self._obs(), np.where(resetting, 0.0, 1.0), terminated, truncated, info


def test_training_loop_stores_no_transition_across_an_autoreset(tmp_path):
    config = TrainConfig(
        inputs="lidar",
        num_envs=3,
        total_steps=400,
        run_dir=tmp_path,
        progress=False,
        dqn=tiny_dqn(learning_starts=50),
    )
    summary = train(config, envs=CountingEnv(3))
    assert summary["episodes"] > 10
    saved = saved_replay(tmp_path)
    frames, has_next = saved["frame_lidar"], saved["has_next"]
    ep_step, count = saved["ep_step"], saved["count"]
    assert has_next.sum() == summary["steps"]
    for env in range(3):
        for j in range(int(count[env]) - 1):
            now, nxt = frames[env, j], frames[env, j + 1]
            assert now[0] == env and ep_step[env, j] == now[2]
            if has_next[env, j]:  # a transition: same episode, the next step
                assert nxt[1] == now[1] and nxt[2] == now[2] + 1
            else:  # an episode's end: the next frame starts the next one
                assert nxt[1] == now[1] + 1 and nxt[2] == 0 and ep_step[env, j + 1] == 0


def saved_replay(run_dir: Path) -> dict[str, np.ndarray]:
    """A run's replay as its files and its last checkpoint hold it."""
    saved = {path.stem: np.load(path) for path in (run_dir / "replay").glob("*.npy")}
    state = load_checkpoint(run_dir / CHECKPOINT_NAME).resume["replay"]
    return {**saved, "count": state["count"].numpy(), "pos": state["pos"].numpy()}


def _last_train_line(run_dir: Path) -> dict:
    lines = [json.loads(x) for x in (run_dir / "metrics.jsonl").read_text().splitlines()]
    return [line for line in lines if line["kind"] == "train"][-1]


def test_a_run_stores_exactly_its_budget_when_the_last_step_would_pass_it(tmp_path):
    """Three environments and a budget of 100: the 34th vector step plays 3 transitions where
    1 is left. It stores that one (environment 0's), and the summary, the checkpoint, the
    last log line and the replay all say 100."""
    config = TrainConfig(
        inputs="lidar",
        num_envs=3,
        total_steps=100,
        run_dir=tmp_path,
        progress=False,
        log_every=40,
        dqn=tiny_dqn(learning_starts=50),
    )
    summary = train(config, envs=PickTheFreeLane(3, length=1000))
    assert summary["steps"] == 100 and summary["unstored"] == 2
    assert summary["env_steps_called"] == 34
    assert load_checkpoint(tmp_path / CHECKPOINT_NAME).step == 100
    assert _last_train_line(tmp_path)["step"] == 100
    saved = saved_replay(tmp_path)
    assert saved["has_next"].sum() == 100
    assert saved["has_next"].sum(axis=1).tolist() == [34, 33, 33]
    # A resume to a larger budget carries on from exactly 100.
    more = train(replace(config, total_steps=131, resume=True), envs=PickTheFreeLane(3))
    assert more["steps"] == 131 and more["resumed_at_step"] == 100


def test_an_episode_ending_past_the_budget_is_not_counted(tmp_path):
    """Episodes of 4 decisions on 2 environments, a budget of 7: the fourth step's second
    transition ends environment 1's episode, but is past the budget: one episode, not two."""
    config = TrainConfig(
        inputs="lidar",
        num_envs=2,
        total_steps=7,
        run_dir=tmp_path,
        progress=False,
        dqn=tiny_dqn(learning_starts=50),
    )
    summary = train(config, envs=PickTheFreeLane(2, length=4))
    assert summary["steps"] == 7 and summary["unstored"] == 1 and summary["episodes"] == 1
    lines = [json.loads(x) for x in (tmp_path / "metrics.jsonl").read_text().splitlines()]
    assert [line["env"] for line in lines if line["kind"] == "episode"] == [0]


@pytest.mark.parametrize("overlap, parts", [("off", 1), ("on", 1), ("on", 2)])
def test_a_remote_run_stores_exactly_its_budget(tmp_path, start_server, overlap, parts):
    server = start_server(f"budget-{overlap}-{parts}")
    run_dir = tmp_path / "run"
    summary = train(
        TrainConfig(
            inputs="lidar",
            num_envs=3,
            total_steps=100,
            seed=2,
            connect=server.endpoint,
            overlap=overlap,
            overlap_parts=parts,
            run_dir=run_dir,
            progress=False,
            log_every=30,
            set=("episode.max_decisions=500",),
            dqn=DQNConfig(**SMOKE_DQN),
        )
    )
    assert summary["steps"] == 100 and summary["parts"] == parts
    assert load_checkpoint(run_dir / CHECKPOINT_NAME).step == 100
    assert _last_train_line(run_dir)["step"] == 100


def test_eval_table_joins_earlier_results_and_refuses_other_files(tmp_path, capsys):
    for seed in (3, 4):
        evaluate(
            EvalConfig(
                policy="random",
                episodes=1,
                max_decisions=20,
                seed=seed,
                name=f"random-{seed}",
                json_out=tmp_path / f"r{seed}.json",
            )
        )
    capsys.readouterr()
    evaluate(EvalConfig(table=(tmp_path / "r3.json", tmp_path / "r4.json")))
    lines = capsys.readouterr().out.splitlines()
    assert lines[2].split()[0] == "random-3" and lines[3].split()[0] == "random-4"
    (tmp_path / "bad.json").write_text("{}")
    with pytest.raises(UsageError, match="not an overtake-eval result"):
        evaluate(EvalConfig(table=(tmp_path / "bad.json",)))


def test_evaluation_does_not_import_the_training_command():
    """overtake-eval reads the library modules, not another command's module."""
    code = (
        "import json, sys, overtake.trainers.evaluate; "
        "print(json.dumps([m for m in sys.modules if m.startswith('overtake.')]))"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    loaded = set(json.loads(done.stdout))
    assert "overtake.trainers.observations" in loaded
    assert (
        "overtake.trainers.train" not in loaded and "overtake.client.episodes.drive" not in loaded
    )


def test_training_writes_a_rerun_recording_of_its_episodes_and_learning(tmp_path):
    import rerun as rr

    config = TrainConfig(
        inputs="lidar",
        num_envs=2,
        total_steps=300,
        run_dir=tmp_path / "run",
        progress=False,
        log_every=100,
        dqn=tiny_dqn(learning_starts=50),
        recording=RecordingConfig(record_every=3),
    )
    envs = WatchEnvZero(PickTheFreeLane(2, length=16))
    train(config, envs=envs)
    records = [
        json.loads(line) for line in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()
    ]
    reader = rr.chunk.RrdReader(str(tmp_path / "run" / "trainer.rrd"))
    assert reader.recordings() and reader.blueprints()

    def series(entity: str) -> tuple[list[int], list[float]]:
        """The scalars logged at ``entity`` (or, ending in ``/*``, any entity under it)."""
        steps, values = [], []
        for chunk in reader.stream().to_chunks():
            path = chunk.entity_path
            wanted = path.startswith(entity[:-1]) if entity.endswith("/*") else path == entity
            if not wanted or chunk.is_static:
                continue
            batch = chunk.to_record_batch()
            steps += batch.column("step").to_pylist()
            values += [v[0] for v in batch.column("Scalars:scalars").to_pylist()]
        order = np.argsort(steps, kind="stable")
        return [steps[i] for i in order], [values[i] for i in order]

    returns = [r for r in records if r["kind"] == "episode"]
    # Metric first, run second: runs sharing a recording fall into the same plots.
    steps, values = series("/training/episode/return/run")
    assert steps == [r["step"] for r in returns]
    assert values == pytest.approx([r["return"] for r in returns])
    trained = [r for r in records if r["kind"] == "train" and r["loss"] is not None]
    steps, values = series("/training/learning/loss/run")
    assert steps == [r["step"] for r in trained] and len(steps) >= 2
    assert values == pytest.approx([r["loss"] for r in trained])
    _, epsilons = series("/training/learning/epsilon/run")
    assert epsilons == sorted(epsilons, reverse=True) and epsilons[0] <= 1.0

    # Environment 0's view, every 3rd step of the vector env, skipping autoreset steps: the
    # LIDAR it was shown, the action it took and the reward it got for it.
    expected = [
        (seen, action, reward)
        for i, (seen, action, reward, resetting) in enumerate(envs.log)
        if i % 3 == 0 and not resetting
    ]
    _, rewards = series("/trainer/run/env0/reward/total")
    _, actions = series("/trainer/run/env0/action/*")  # a series per action, its index the value
    _, chosen_q = series("/trainer/run/env0/q_chosen")
    hits = []
    for chunk in reader.stream().to_chunks():
        if chunk.entity_path == "/trainer/run/env0/lidar/hits" and not chunk.is_static:
            batch = chunk.to_record_batch()
            hits += zip(
                batch.column("step").to_pylist(), batch.column("Points2D:positions").to_pylist()
            )
    hits = [np.asarray(points) for _, points in sorted(hits, key=lambda h: h[0])]
    assert len(expected) == len(rewards) == len(actions) == len(hits) == len(chosen_q) > 30
    assert rewards == pytest.approx([r for _, _, r in expected])
    assert actions == [a for _, a, _ in expected]
    angles = np.arange(5) * (2 * np.pi / 5)
    for points, (seen, _, _) in zip(hits, expected):
        assert np.hypot(points[:, 0], points[:, 1]) == pytest.approx(seen, rel=1e-5)
        # Drawn as a map: x ahead, the car's left up (Rerun's +y points down).
        assert np.allclose(
            points, np.stack([seen * np.cos(angles), -seen * np.sin(angles)], 1), atol=1e-4
        )


@contextlib.contextmanager
def _long_ho2018_run(run_dir: Path, *options: str) -> Iterator[tuple[subprocess.Popen, Path]]:
    """An overtake-train run of ho2018 too long to end by itself, logging every 40 steps and
    checkpointing only when stopped (its replay in memory: a small replay on disk asks for a
    checkpoint whenever its spare slots are taken), once it has logged twice; with the file
    its stderr goes to (read while it runs). Killed on the way out if still running."""
    from tests.support.remote import child_env, wait_until

    errors_file = run_dir.parent / "trainer.err"
    with errors_file.open("w") as errors_out:
        trainer = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "overtake.trainers.train",
                *("--preset", "ho2018", "--total-steps", "1000000", *options),
                *("--run-dir", str(run_dir), "--no-progress", "--log-every", "40"),
                *("--checkpoint-every", "1000000", "--learning-starts", "64"),
                *("--replay-size", "500", "--hidden-units", "32", "--torch-threads", "1"),
                "--no-replay-on-disk",
            ],
            stdout=subprocess.PIPE,
            stderr=errors_out,
            text=True,
            env=child_env(),
        )
    metrics = run_dir / "metrics.jsonl"
    try:
        wait_until(
            lambda: metrics.exists() and metrics.read_text().count("\n") >= 2, 90, "two log lines"
        )
        yield trainer, errors_file
    finally:
        if trainer.poll() is None:
            trainer.kill()
            trainer.wait()


def _sigterm(trainer: subprocess.Popen, errors_file: Path, timeout_s: float) -> tuple[str, str]:
    """SIGTERM to ``trainer``; its stdout and stderr once it has ended."""
    import signal

    trainer.send_signal(signal.SIGTERM)
    out, _ = trainer.communicate(timeout=timeout_s)
    return out, errors_file.read_text()


@pytest.mark.timeout(120)
def test_sigterm_ends_a_remote_run_whose_server_is_gone_with_its_checkpoint(tmp_path, start_server):
    """docker compose stop after the server died: the step under way waits on a server that is
    gone (its round, then a server to reopen the arenas on, for the reconnect timeout); the
    stop ends that wait and the run ends as a stopped run does, with its checkpoint, status 0.
    Without it the trainer waited out the reconnect timeout and failed, checkpoint unwritten."""
    from tests.support.remote import wait_until

    server = start_server("gone")
    run_dir = tmp_path / "run"
    with _long_ho2018_run(run_dir, "--connect", server.endpoint) as (trainer, errors_file):
        server.kill()  # gone without a word
        # The stop must find the trainer waiting for a server to reopen its arena on.
        wait_until(lambda: "reopening" in errors_file.read_text(), 60, "the trainer to notice")
        out, err = _sigterm(trainer, errors_file, 90)
    assert trainer.returncode == 0, err
    assert "the run ends at its last whole step" in err
    summary = json.loads(out[out.index("{") :])
    assert summary["stopped"] is True
    assert load_checkpoint(run_dir / CHECKPOINT_NAME).step == summary["steps"] > 0


@pytest.mark.timeout(120)
def test_sigterm_ends_a_training_run_with_a_checkpoint_and_a_whole_recording(tmp_path):
    # docker compose stop, a cluster's preemption, Ctrl-C: the run ends after the step under
    # way as it would at --total-steps, so nothing since the last periodic checkpoint is lost
    # and the .rrd is closed with everything in it: the last log line, written at the stop
    # (a killed writer's file lacks what it had not flushed).
    run_dir = tmp_path / "run"
    with _long_ho2018_run(run_dir, "--seed", "3") as (trainer, errors_file):
        assert not (run_dir / CHECKPOINT_NAME).exists()  # none periodic: the stop writes it
        out, err = _sigterm(trainer, errors_file, 60)
    assert trainer.returncode == 0, err
    assert "SIGTERM: finishing the step under way, writing a checkpoint" in err
    summary = json.loads(out[out.index("{") :])
    assert summary["stopped"] is True and 80 <= summary["steps"] < 1_000_000
    assert load_checkpoint(run_dir / CHECKPOINT_NAME).step == summary["steps"]
    # Written without a footer (a run may write for days: overtake.viz.recording, on footers).
    verified = subprocess.run(
        [
            str(Path(sys.executable).with_name("rerun")),
            "rrd",
            "verify",
            "--check-footers",
            "false",
            str(run_dir / "trainer.rrd"),
        ],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert verified.returncode == 0, verified.stderr
    from overtake.viz.layout import open_reader

    epsilon_steps = [
        step
        for chunk in open_reader(run_dir / "trainer.rrd").stream().to_chunks()
        if chunk.entity_path == "/training/learning/epsilon/run" and not chunk.is_static
        for step in chunk.to_record_batch().column("step").to_pylist()
    ]
    assert max(epsilon_steps) == summary["steps"]  # the stop's own log line


def test_overlap_auto_leaves_a_core_for_the_server(monkeypatch):
    """--overlap auto learns while the server simulates only where this machine has a core
    beyond PyTorch's threads; on and off decide by themselves; in-process never overlaps."""
    remote = TrainConfig(connect="tcp/127.0.0.1:7447", num_envs=4, overlap_parts=2)
    monkeypatch.setattr("os.cpu_count", lambda: 4)
    monkeypatch.setattr(torch, "get_num_threads", lambda: 4)
    assert not remote.overlapped and remote.parts == 1
    monkeypatch.setattr(torch, "get_num_threads", lambda: 3)
    assert remote.overlapped and remote.parts == 2
    assert not replace(remote, overlap="off").overlapped
    monkeypatch.setattr(torch, "get_num_threads", lambda: 4)
    assert replace(remote, overlap="on").parts == 2
    assert not replace(remote, connect=None, overlap="on").overlapped
    # Never more parts than environments.
    assert replace(remote, overlap="on", num_envs=1).parts == 1


def test_an_in_process_run_draws_its_first_cars_road_in_its_recording(tmp_path):
    """World frames leave only a server: in-process, the trainer draws environment 0's road
    itself (every car on it), and its layout shows the road beside the car's view."""
    import rerun as rr

    from overtake.trainers.run_recording import IN_PROCESS_ROAD

    from tests.support.remote import blueprint_texts

    config = TrainConfig(
        inputs="lidar",
        num_envs=2,
        total_steps=60,
        run_dir=tmp_path / "run",
        progress=False,
        set=("episode.max_decisions=40",),
        dqn=tiny_dqn(learning_starts=50),
        recording=RecordingConfig(record_every=5),
    )
    train(config)
    reader = rr.chunk.RrdReader(str(tmp_path / "run" / "trainer.rrd"))
    cars = [
        chunk.to_record_batch()
        for chunk in reader.stream().to_chunks()
        if chunk.entity_path == f"{IN_PROCESS_ROAD}/cars" and not chunk.is_static
    ]
    # A frame every 5th step of the vector env: 60 steps of 2 envs are 30 steps, 6 frames
    # (and the same count of car views), each with the agent and the medium traffic's cars.
    boxes = [len(row) for batch in cars for row in batch.column("Boxes2D:half_sizes").to_pylist()]
    assert len(boxes) == 6 and all(count > 10 for count in boxes), boxes
    texts = set().union(*(blueprint_texts(reader, store) for store in reader.blueprints()))
    assert IN_PROCESS_ROAD in texts and "run: road (env 0 at 0 m, left up)" in texts
