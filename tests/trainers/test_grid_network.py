"""Ho's two Q-networks on the occupancy grid (Figs. 4-5): their shapes as the thesis and his
code give them, the action stack read only by the proposed one, and both able to learn."""

from __future__ import annotations

import pytest
import torch

from overtake.trainers.grid_network import GridNetworkShape, GridQNetwork
from overtake.trainers.heads import HeadSpec

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
