"""Ho's two Q-networks on the occupancy grid (Figs. 4-5): their shapes as the thesis and his
code give them, the action stack read only by the proposed one, and both able to learn."""

from __future__ import annotations

import pytest
import torch

from overtake.trainers.learning.grid_network import GridNetworkShape, GridQNetwork
from overtake.trainers.learning.heads import HeadSpec

SHAPE = GridNetworkShape(grid_hw=(36, 3), action_history=4, actions=5, stack=4)


@pytest.fixture(autouse=True, scope="module")
def one_thread():
    # Small networks on a busy 2-core machine: a second intra-op thread only contends.
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def inputs(batch: int = 6, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    generator = torch.Generator().manual_seed(seed)
    grid = torch.randint(-1, 2, (batch, 4, 36, 3), generator=generator, dtype=torch.int8)
    actions = torch.randint(0, 5, (batch, 4), generator=generator).float()
    return grid, actions


@pytest.mark.parametrize("kind", ["baseline", "proposed"])
@pytest.mark.parametrize("dueling", [False, True])
def test_q_values_per_action(kind, dueling):
    grid, actions = inputs()
    head = HeadSpec("dueling" if dueling else "plain")
    q = GridQNetwork(SHAPE, kind, head=head)(grid, actions)
    assert q.shape == (6, 5) and torch.isfinite(q).all()


def test_the_layers_have_the_sizes_of_the_thesis_and_his_code():
    baseline = GridQNetwork(SHAPE, "baseline")
    # One convolution 16 x 3x3 x 4 channels (+16), stride 2: 18 x 2 cells; one linear layer.
    assert sum(p.numel() for p in baseline.parameters()) == (16 * 9 * 4 + 16) + (
        16 * 18 * 2 * 5 + 5
    )
    proposed = GridQNetwork(SHAPE, "proposed")
    # His code: 9 x 1 x 32 features after two poolings, 4-4 for the actions, 100 hidden.
    assert proposed.fuse[0].in_features == 9 * 1 * 32 + 4
    assert proposed.fuse[0].out_features == 100


def test_only_the_proposed_network_reads_the_action_stack():
    # Seeded: from some starting weights the action stack's small ReLU layers output zero for
    # both stacks, and the network then reads neither (the test failed by the order it ran in).
    torch.manual_seed(0)
    grid, actions = inputs()
    other = actions.flip(0)
    baseline, proposed = GridQNetwork(SHAPE, "baseline"), GridQNetwork(SHAPE, "proposed")
    assert torch.equal(baseline(grid, actions), baseline(grid, other))
    assert not torch.equal(proposed(grid, actions), proposed(grid, other))
    with pytest.raises(AssertionError, match="action stack"):
        proposed(grid)


def test_a_grid_network_fits_q_values_that_depend_on_the_grid():
    torch.manual_seed(0)
    network = GridQNetwork(SHAPE, "proposed")
    grid, actions = inputs(batch=64, seed=1)
    # A target a network blind to the grid cannot fit: Q of action 0 is the own lane's
    # occupancy ahead.
    target = torch.zeros(64, 5)
    target[:, 0] = grid[:, -1, :24, 1].float().clamp(min=0).sum(dim=1)
    optimiser = torch.optim.Adam(network.parameters(), lr=3e-3)
    first = None
    for _ in range(300):
        loss = torch.nn.functional.mse_loss(network(grid, actions), target)
        first = loss.item() if first is None else first
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
    assert loss.item() < 0.1 * first


# --- Ho's initialisation (cnn.py: tf.truncated_normal_initializer(stddev=2e-2)) ------------------


def _layers(network: torch.nn.Module) -> list[torch.nn.Module]:
    return [m for m in network.modules() if isinstance(m, (torch.nn.Conv2d, torch.nn.Linear))]


@pytest.mark.parametrize("kind", ["baseline", "proposed"])
@pytest.mark.parametrize("head", ["plain", "dueling"])
def test_his_initialisation_cuts_every_kernel_at_two_deviations_and_zeroes_the_biases(kind, head):
    torch.manual_seed(0)
    network = GridQNetwork(SHAPE, kind, head=HeadSpec(head), init_std=0.02)
    layers = _layers(network)
    assert len(layers) == {"baseline": 2, "proposed": 6}[kind] + (head == "dueling")
    for layer in layers:  # every convolution and dense layer, the head's included
        assert layer.weight.abs().max() <= 0.04
        assert layer.bias is not None and (layer.bias == 0).all()


def test_his_initialisation_has_the_deviation_of_a_normal_cut_at_two():
    # A normal of deviation 0.02 redrawn beyond +-0.04 keeps 0.8796 of its deviation; the fused
    # layer's 292 x 100 weights measure it to within 1%.
    torch.manual_seed(1)
    fused = GridQNetwork(SHAPE, "proposed", init_std=0.02).fuse[0].weight
    assert fused.numel() == 29_200
    assert fused.std().item() == pytest.approx(0.02 * 0.8796, rel=0.01)
    assert fused.mean().abs().item() < 0.0005
    # PyTorch's own start (Kaiming-uniform: bound 1 / sqrt(292)) is another distribution.
    torch.manual_seed(1)
    default = GridQNetwork(SHAPE, "proposed").fuse[0]
    assert default.weight.abs().max().item() > 0.05 and (default.bias != 0).any()


def test_the_learner_builds_his_initialisation_from_its_settings_and_refuses_it_elsewhere():
    from dataclasses import replace

    from overtake.trainers.config.presets import PRESET_TRAINING
    from overtake.trainers.learning.heads import PLAIN
    from overtake.trainers.learning.learner import build_network

    dqn = PRESET_TRAINING["ho2018"].dqn
    assert (dqn.init, dqn.init_std) == ("truncated-normal", 0.02)
    built = build_network(SHAPE, "grid", dqn, PLAIN)
    assert all(layer.weight.abs().max() <= 0.04 for layer in _layers(built))
    assert all((layer.bias == 0).all() for layer in _layers(built))
    torch_init = build_network(SHAPE, "grid", replace(dqn, init="torch"), PLAIN)
    assert any((layer.bias != 0).any() for layer in _layers(torch_init))
    with pytest.raises(ValueError, match="init truncated-normal is Ho's"):
        build_network(SHAPE, "lidar", replace(dqn, network="multimodal"), PLAIN)
    with pytest.raises(ValueError, match="init must be one of"):
        replace(dqn, init="xavier")
