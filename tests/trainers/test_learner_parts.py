"""The learner's parts: heads that every network ends in, objectives that own their targets, and
QR-DQN built from them (a quantile head and the quantile Huber loss) with no network changed."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from overtake.trainers.learning.grid_network import GridNetworkShape, GridQNetwork
from overtake.trainers.learning.heads import HeadSpec, QuantileHead, legacy_state
from overtake.trainers.learning.learner import ALGOS, DQNConfig, DQNLearner
from overtake.trainers.learning.network import NetworkShape, QNetwork
from overtake.trainers.learning.objectives import QuantileObjective, TDObjective, Transitions
from overtake.trainers.learning.replay_memory import ReplayBatch
from overtake.trainers.learning.two_stream_network import TwoStreamQNetwork, TwoStreamShape


def transitions(action, reward, terminated, mask, gamma=0.9) -> Transitions:
    return Transitions(
        action=torch.tensor(action),
        reward=torch.tensor(reward, dtype=torch.float32),
        terminated=torch.tensor(terminated),
        next_mask=torch.tensor(mask),
        gamma=gamma,
    )


def test_every_network_ends_in_whichever_head_it_is_given():
    grid = GridNetworkShape(grid_hw=(36, 3), actions=5, stack=4, action_history=4)
    two = TwoStreamShape((40, 40, 3), (40, 40), 5, 4)
    lidar = NetworkShape(camera_hw=(36, 36), lidar_rays=8, ego_size=6, actions=5, stack=4)
    inputs = {
        "grid": (torch.zeros(2, 4, 36, 3), torch.zeros(2, 4)),
        "two": (torch.zeros(2, 4, 40, 40, 3, dtype=torch.uint8), torch.zeros(2, 4, 40, 40)),
        "lidar": (None, torch.zeros(2, 4, 8), torch.zeros(2, 6)),
    }
    for kind, shape in (("plain", (2, 5)), ("dueling", (2, 5)), ("quantile", (2, 5, 7))):
        head = HeadSpec(kind, quantiles=7)
        networks = {
            "grid": GridQNetwork(grid, "proposed", head=head),
            "two": TwoStreamQNetwork(two, head=head),
            "lidar": QNetwork(lidar, "lidar", head=head, lstm_cells=8, hidden=16),
        }
        for name, network in networks.items():
            out = network(*inputs[name])
            assert out.shape == shape, (kind, name)
            assert network.head.q(out).shape == (2, 5)


def test_a_quantile_head_reads_as_the_mean_of_its_quantiles_at_the_midpoints():
    head = QuantileHead(4, actions=2, quantiles=4)
    out = head(torch.randn(3, 4))
    assert out.shape == (3, 2, 4)
    assert torch.allclose(head.q(out), out.mean(dim=-1))
    assert head.taus(torch.device("cpu")).tolist() == [0.125, 0.375, 0.625, 0.875]


def test_the_quantile_target_is_the_chosen_next_actions_quantiles_shifted_and_scaled():
    head = QuantileHead(1, actions=3, quantiles=2)
    objective = QuantileObjective(head, double=True, kappa=1.0)
    # Next state: the online network prefers action 1 by mean, but it is masked out; of the
    # allowed 0 and 2 it prefers 2. The target network's quantiles of action 2: [1, 3].
    next_online = torch.tensor([[[0.0, 0.0], [9.0, 9.0], [1.0, 2.0]]] * 2)
    next_target = torch.tensor([[[5.0, 5.0], [7.0, 7.0], [1.0, 3.0]]] * 2)
    online = torch.zeros(2, 3, 2, requires_grad=True)
    batch = transitions([0, 0], [1.0, 1.0], [False, True], [[1, 0, 1]] * 2, gamma=0.5)
    terms = objective.terms(online, next_target, next_online, batch)
    # Target quantiles: 1 + 0.5 * [1, 3] = [1.5, 2.5]; terminated: [1, 1].
    # Estimates 0 against targets [1.5, 2.5] at taus [0.25, 0.75], kappa 1: each u > 0, the
    # Huber value |u| - 0.5 (1.0, 2.0) weighted by tau; summed over estimates, averaged over
    # targets: (0.25 + 0.75) * (1.0 + 2.0) / 2 = 1.5. Terminated: u = 1, Huber 0.5: 0.5.
    assert terms.loss.tolist() == pytest.approx([1.5, 0.5])
    assert terms.td_error.tolist() == pytest.approx([2.0, 1.0])
    terms.loss.sum().backward()
    assert online.grad is not None and online.grad[:, 1:].abs().sum() == 0  # the taken action


def test_below_the_threshold_the_quantile_loss_is_quadratic_and_asymmetric():
    head = QuantileHead(1, actions=1, quantiles=1)  # one quantile: the median, tau 0.5
    objective = QuantileObjective(head, double=False, kappa=1.0)
    target = torch.tensor([[[0.0]]])
    for estimate, expected in ((0.4, 0.5 * 0.5 * 0.16), (-0.4, 0.5 * 0.5 * 0.16)):
        online = torch.tensor([[[estimate]]])
        terms = objective.terms(online, target, None, transitions([0], [0.0], [True], [[1]]))
        assert terms.loss.item() == pytest.approx(expected)


def test_the_td_objective_is_the_double_target_of_before():
    head = HeadSpec("plain").build(1, 3)
    objective = TDObjective(head, double=True, loss="mse", huber_delta=1.0)
    online = torch.tensor([[1.0, 2.0, 3.0]])
    next_online = torch.tensor([[0.0, 5.0, 1.0]])
    next_target = torch.tensor([[4.0, 2.0, 8.0]])
    batch = transitions([1], [1.0], [False], [[1, 1, 1]], gamma=0.5)
    terms = objective.terms(online, next_target, next_online, batch)
    # Online picks action 1; the target values it 2: target 1 + 0.5 * 2 = 2, Q taken 2.
    assert terms.q_taken.tolist() == [2.0] and terms.loss.tolist() == [0.0]


def test_qr_dqn_learns_to_tell_a_good_action_from_a_bad_one():
    torch.manual_seed(0)
    shape = NetworkShape(camera_hw=(36, 36), lidar_rays=4, ego_size=1, actions=2, stack=1)
    config = DQNConfig(lstm_cells=8, hidden_units=16, quantiles=5, learning_rate=0.01)
    learner = DQNLearner(shape, "lidar", config, ALGOS["qr"])
    rng = np.random.default_rng(0)
    for _ in range(300):
        action = rng.integers(0, 2, 32)
        obs = {"lidar": np.ones((32, 1, 4), np.float32), "ego": np.zeros((32, 1), np.float32)}
        learner.update(
            ReplayBatch(
                obs=obs,
                next_obs=obs,
                action=action,
                reward=np.where(action == 1, 1.0, -1.0).astype(np.float32),
                terminated=np.ones(32, dtype=bool),
                steps=np.ones(32, dtype=np.int64),
                next_mask=np.ones((32, 2), dtype=np.int8),
            )
        )
    q = learner.q_values(
        {"lidar": np.ones((1, 1, 4), np.float32), "ego": np.zeros((1, 1), np.float32)}
    )
    assert q[0, 1] == pytest.approx(1.0, abs=0.2) and q[0, 0] == pytest.approx(-1.0, abs=0.2)


def test_a_checkpoint_from_before_heads_were_parts_loads_its_head():
    shape = NetworkShape(camera_hw=(36, 36), lidar_rays=4, ego_size=1, actions=5, stack=1)
    for algo, names in (("dqn", ("q",)), ("dueling", ("value", "advantage"))):
        config = DQNConfig(lstm_cells=8, hidden_units=16)
        learner = DQNLearner(shape, "lidar", config, ALGOS[algo])
        state = learner.state_dict()
        # As a checkpoint of then named them: the head's layers on the network itself.
        old = {
            part: {
                (
                    k.replace("head.q_layer.", "q.")
                    if k.startswith("head.q_layer.")
                    else k.replace("head.", "")
                ): v
                for k, v in state[part].items()
            }
            for part in ("online", "target")
        }
        assert any(k.split(".")[0] in names for k in old["online"])
        assert legacy_state(old["online"]).keys() == state["online"].keys()
        other = DQNLearner(shape, "lidar", config, ALGOS[algo])
        other.load_state_dict({**state, **old})
        for a, b in zip(other.online.parameters(), learner.online.parameters(), strict=True):
            assert torch.equal(a, b)
