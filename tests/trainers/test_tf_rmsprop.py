"""TensorFlow's RMSProp (Ho's optimiser, trainers/learning/tf_rmsprop.py) against its formulas
worked out by hand, and against PyTorch's RMSProp, which it is not."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from overtake.trainers.config.presets import PRESET_TRAINING
from overtake.trainers.learning.learner import DQNConfig, build_optimizer
from overtake.trainers.learning.tf_rmsprop import TFRMSprop

GRADIENTS = np.array([[0.5, -2.0, 1e-3], [0.1, -1.5, 0.0], [-0.3, 4.0, 2e-3], [0.2, 0.2, 0.2]])


def tensorflow_by_hand(lr, decay, epsilon, centered):
    """ApplyRMSProp / ApplyCenteredRMSProp as training_ops.cc computes them, in float64:
    the mean square starts at one, the moment and the mean gradient at zero."""
    var, ms, mg, mom = np.zeros(3), np.ones(3), np.zeros(3), np.zeros(3)
    for g in GRADIENTS:
        ms = ms + (g * g - ms) * (1 - decay)
        denominator = ms + epsilon
        if centered:
            mg = mg + (g - mg) * (1 - decay)
            denominator = denominator - mg * mg
        mom = lr * g / np.sqrt(denominator)
        var = var - mom
    return var


def run(optimizer_of) -> np.ndarray:
    param = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    optimizer = optimizer_of([param])
    for g in GRADIENTS:
        optimizer.zero_grad()
        param.grad = torch.tensor(g)
        optimizer.step()
    return param.detach().numpy()


@pytest.mark.parametrize("centered", [False, True])
def test_it_is_tensorflows_rmsprop(centered):
    got = run(lambda p: TFRMSprop(p, lr=0.01, decay=0.9, epsilon=1e-10, centered=centered))
    np.testing.assert_allclose(got, tensorflow_by_hand(0.01, 0.9, 1e-10, centered), rtol=1e-12)


def test_it_differs_from_pytorchs_where_tensorflow_differs():
    ours = run(lambda p: TFRMSprop(p, lr=0.01))
    pytorchs = run(lambda p: torch.optim.RMSprop(p, lr=0.01, alpha=0.9, eps=1e-10))
    # The mean square starting at one makes TensorFlow's first steps about lr * g, PyTorch's
    # about lr * sign(g) / sqrt(0.1): over three times larger.
    assert np.all(np.abs(pytorchs) > 2 * np.abs(ours))


def test_its_state_survives_a_checkpoint():
    a = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    first = TFRMSprop([a], lr=0.01)
    a.grad = torch.tensor(GRADIENTS[0])
    first.step()
    b = a.detach().clone().requires_grad_(True)
    second = TFRMSprop([b], lr=0.01)
    second.load_state_dict(copy.deepcopy(first.state_dict()))  # as if read from a file
    for optimizer, param in ((first, a), (second, b)):
        param.grad = torch.tensor(GRADIENTS[1])
        optimizer.step()
    assert torch.equal(a, b)


def test_ho2018_trains_with_it_every_decision_as_his_code_does():
    dqn = PRESET_TRAINING["ho2018"].dqn
    assert (dqn.optimizer, dqn.rmsprop_alpha, dqn.rmsprop_eps, dqn.rmsprop_centered) == (
        "tf-rmsprop",
        0.9,
        1e-10,
        False,
    )
    assert (dqn.train_every, dqn.batch_size, dqn.replay_size) == (1, 32, 1_000_000)
    assert (dqn.target_update_steps, dqn.epsilon_decay_steps, dqn.learning_starts) == (
        10_000,
        2_000_000,
        100_000,
    )
    optimizer = build_optimizer([torch.zeros(2, requires_grad=True)], dqn)
    assert isinstance(optimizer, TFRMSprop)
    with pytest.raises(ValueError, match="decay"):
        TFRMSprop([torch.zeros(1, requires_grad=True)], lr=0.01, decay=1.0)
    with pytest.raises(ValueError, match="optimizer must be one of"):
        DQNConfig(optimizer="tf-adam")  # type: ignore[arg-type]


def _network_steps(one_buffer: bool, centered: bool, state=None, steps: int = 5):
    torch.manual_seed(0)
    network = torch.nn.Sequential(
        torch.nn.Conv2d(2, 4, 3, padding=1), torch.nn.ReLU(), torch.nn.Flatten(),
        torch.nn.Linear(4 * 6 * 3, 5),
    )  # fmt: skip
    optimizer = TFRMSprop(network.parameters(), lr=1e-3, centered=centered, one_buffer=one_buffer)
    if state is not None:
        network.load_state_dict(state[0])
        optimizer.load_state_dict(copy.deepcopy(state[1]))
    generator = torch.Generator().manual_seed(1)
    for _ in range(steps):
        optimizer.zero_grad(set_to_none=True)
        network(torch.randn(8, 2, 6, 3, generator=generator)).pow(2).mean().backward()
        optimizer.step()
    return network, optimizer


@pytest.mark.parametrize("centered", [False, True])
def test_one_buffer_steps_bit_for_bit_as_a_buffer_a_parameter(centered):
    """The parameters moved into one buffer (build_optimizer's choice): the same weights and
    slots after five steps, and its state dict loads into the other layout and back, each
    going on as the other."""
    flat_net, flat = _network_steps(True, centered)
    each_net, each = _network_steps(False, centered)
    for a, b in zip(flat_net.parameters(), each_net.parameters(), strict=True):
        assert torch.equal(a, b)
    for a, b in zip(flat.state.values(), each.state.values(), strict=True):
        assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    # The gradients stayed the buffer's views: autograd added into them, nothing copied in.
    buffers = flat._buffers[0]
    assert all(p.grad is g for p, g in zip(flat_net.parameters(), buffers.grad_views, strict=True))
    saved = (each_net.state_dict(), each.state_dict())
    flat_after, _ = _network_steps(True, centered, state=saved, steps=3)
    each_after, _ = _network_steps(
        False, centered, state=(flat_net.state_dict(), flat.state_dict()), steps=3
    )
    for a, b in zip(flat_after.parameters(), each_after.parameters(), strict=True):
        assert torch.equal(a, b)


def test_one_buffer_starts_afresh_from_a_never_stepped_state_dict():
    """A state dict of an optimiser that never stepped starts the slots afresh."""
    net, optimizer = _network_steps(True, False)
    fresh = TFRMSprop(torch.nn.Linear(2, 2).parameters(), lr=1e-3).state_dict()
    fresh["param_groups"][0]["params"] = list(range(len(list(net.parameters()))))
    optimizer.load_state_dict(fresh)
    assert torch.equal(
        optimizer._buffers[0].slots["ms"], torch.ones_like(optimizer._buffers[0].slots["ms"])
    )
