"""The learner: DQN and Double DQN targets, the dueling network, masking, acting, updates,
devices and precisions; and that it learns a purpose-built tiny environment.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from overtake.trainers.learning.heads import HeadSpec, dueling_q
from overtake.trainers.learning.learner import ALGOS, DQNConfig, DQNLearner, execution_device
from overtake.trainers.learning.network import NetworkShape, QNetwork
from overtake.trainers.learning.objectives import masked, td_target
from overtake.trainers.run.checkpoint import CHECKPOINT_NAME
from overtake.trainers.train import TrainConfig
from overtake.trainers.train import main as train

from tests.support.tiny_learning import (
    PickTheFreeLane,
    greedy_score,
    random_obs,
    reward_three_for_action_two,
    small_shape,
    tiny_dqn,
)

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


# --- a purpose-built tiny environment: the learner learns ----------------------------------------


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
