"""Ho's Q-networks (2018, §5, Figs. 4-5) on the occupancy grid and the action stack.

- ``baseline`` (Fig. 4, after Mnih et al. 2013): the last ``stack`` grids (B, S, cells, lanes)
  as channels, one convolution of 16 filters 3x3 with stride 2 and ReLU, flattened, one linear
  layer to the Q-values. The thesis gives no padding: 1 here, so that the three lanes survive.
- ``proposed`` (Fig. 5; the sizes are his code's): two convolutions of 16 and 32 filters 3x3
  (padding 1), each with ReLU and a 2x2 max pooling of stride 2 (rounding up, TensorFlow's
  "same"), flattened; the action stack (the last four actions, as action indices, the way his
  code feeds them) through two dense layers of 4 units with ReLU; both concatenated, a dense
  layer of 100 units with ReLU, then the Q-values.

The last layer is the head a :class:`~.heads.HeadSpec` names (Ho used plain Q-values; dueling
streams or QR-DQN's quantiles are options, :mod:`.heads`). Grids arrive as the simulator sends
them (int8: -1 off the road, 0 free, 1 occupied) and are read as numbers unchanged.

The weights start as PyTorch's layers start them, or (``init_std``, :func:`truncated_normal_`)
as Ho's ``cnn.py`` starts them: every convolution's and dense layer's kernel, the head's
included, from ``tf.truncated_normal_initializer(stddev=0.02)`` (a normal redrawn outside two
standard deviations), the biases zero (``tf.layers``' default).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
from torch import nn

from .heads import PLAIN, HeadSpec

GridNetworkKind = Literal["baseline", "proposed"]
GRID_NETWORKS: tuple[str, ...] = ("baseline", "proposed")


@dataclass(frozen=True)
class GridNetworkShape:
    """What a grid network is built for: one grid's (cells, lanes), the action stack's
    length, the action count and the grids stacked per observation."""

    grid_hw: tuple[int, int]
    action_history: int
    actions: int
    stack: int = 4

    @classmethod
    def from_space(cls, space, actions: int, stack: int) -> GridNetworkShape:
        """From a single environment's Dict observation space (``grid`` and ``actions``)."""
        cells, lanes = space["grid"].shape
        return cls(
            grid_hw=(int(cells), int(lanes)),
            action_history=int(space["actions"].shape[0]),
            actions=actions,
            stack=stack,
        )


def truncated_normal_(module: nn.Module, std: float) -> None:
    """Start every convolution's and linear layer's weights in ``module`` from a normal of
    standard deviation ``std`` cut at two standard deviations (TensorFlow 1.x's
    ``truncated_normal``: values beyond are drawn again, so the weights' own standard
    deviation is about 0.88 ``std``), and their biases at zero."""
    for layer in module.modules():
        if isinstance(layer, (nn.Conv2d, nn.Linear)):
            nn.init.trunc_normal_(layer.weight, mean=0.0, std=std, a=-2 * std, b=2 * std)
            if layer.bias is not None:
                nn.init.zeros_(layer.bias)


def _pooled(size: int) -> int:
    """A length after a 2x2 max pooling of stride 2 that rounds up (TensorFlow's "same")."""
    return (size + 1) // 2


class GridQNetwork(nn.Module):
    """The head's output from stacked grids (B, S, cells, lanes) and the action stack (B, K)."""

    # The observations forward() takes, in order.
    input_names: tuple[str, ...] = ("grid", "actions")

    def __init__(
        self,
        shape: GridNetworkShape,
        kind: GridNetworkKind = "proposed",
        head: HeadSpec = PLAIN,
        init_std: float | None = None,
    ) -> None:
        """``init_std``: Ho's truncated normal of that deviation for the weights
        (:func:`truncated_normal_`); None: PyTorch's initialisation."""
        super().__init__()
        if kind not in GRID_NETWORKS:
            raise ValueError(f"kind must be one of {GRID_NETWORKS}, got {kind!r}")
        self.shape, self.kind = shape, kind
        cells, lanes = shape.grid_hw
        if kind == "baseline":
            self.conv = nn.Sequential(
                nn.Conv2d(shape.stack, 16, kernel_size=3, stride=2, padding=1),
                nn.ReLU(),
                nn.Flatten(),
            )
            features = 16 * ((cells - 1) // 2 + 1) * ((lanes - 1) // 2 + 1)
            self.uses_actions = False
            self.used_inputs: tuple[str, ...] = ("grid",)
            last = features
        else:
            self.conv = nn.Sequential(
                nn.Conv2d(shape.stack, 16, kernel_size=3, padding=1),
                nn.ReLU(),
                nn.MaxPool2d(2, stride=2, ceil_mode=True),
                nn.Conv2d(16, 32, kernel_size=3, padding=1),
                nn.ReLU(),
                nn.MaxPool2d(2, stride=2, ceil_mode=True),
                nn.Flatten(),
            )
            features = 32 * _pooled(_pooled(cells)) * _pooled(_pooled(lanes))
            self.action_net = nn.Sequential(
                nn.Linear(shape.action_history, 4), nn.ReLU(), nn.Linear(4, 4), nn.ReLU()
            )
            self.uses_actions = True
            self.used_inputs = ("grid", "actions")
            self.fuse = nn.Sequential(nn.Linear(features + 4, 100), nn.ReLU())
            last = 100
        self.head = head.build(last, shape.actions)
        # PyTorch's CPU max pooling is 6x faster on channels-last tensors (a 2x2 pool of a batch
        # of (32, 16, 36, 3): 38 against 252 us), which makes a lone update of the proposed
        # network about 20% faster; the baseline, which does not pool, is faster unchanged.
        # (Members' stacked convolutions lay out their own input: stacked_network turns it off.)
        self.channels_last = kind == "proposed"
        if init_std is not None:
            truncated_normal_(self, init_std)

    def forward(self, grid: torch.Tensor, actions: torch.Tensor | None = None) -> torch.Tensor:
        x = grid.float()
        hidden = self.conv(
            x.contiguous(memory_format=torch.channels_last) if self.channels_last else x
        )
        if self.uses_actions:
            assert actions is not None, "the proposed network reads the action stack"
            hidden = self.fuse(torch.cat([hidden, self.action_net(actions.float())], dim=1))
        return self.head(hidden)
