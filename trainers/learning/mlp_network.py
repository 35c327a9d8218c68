"""A multilayer perceptron on highway-env's Kinematics observation (``kinematics`` inputs), as
Stable-Baselines3's ``MlpPolicy`` reads it: the last ``stack`` tables (B, S, cars, features)
flattened, hidden layers with ReLU, then the head a :class:`~.heads.HeadSpec` names. Its
hidden sizes are SB3's documented highway-fast DQN's (``net_arch=[256, 256]``, the
highway-env documentation's example); the table arrives normalised by the sensor.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from .heads import PLAIN, HeadSpec


@dataclass(frozen=True)
class MlpNetworkShape:
    """What the MLP is built for: one table's (cars, features), the action count, the tables
    stacked per observation and the hidden layers' sizes."""

    table_hw: tuple[int, int]
    actions: int
    stack: int = 1
    hidden: tuple[int, ...] = (256, 256)

    @classmethod
    def from_space(cls, space, actions: int, stack: int) -> MlpNetworkShape:
        cars, features = space["kinematics"].shape
        return cls(table_hw=(int(cars), int(features)), actions=actions, stack=stack)


class MlpQNetwork(nn.Module):
    """The head's output from stacked Kinematics tables (B, S, cars, features)."""

    input_names: tuple[str, ...] = ("kinematics",)
    used_inputs: tuple[str, ...] = ("kinematics",)

    def __init__(self, shape: MlpNetworkShape, head: HeadSpec = PLAIN) -> None:
        super().__init__()
        self.shape = shape
        layers: list[nn.Module] = [nn.Flatten()]
        width = shape.stack * int(np.prod(shape.table_hw))
        for size in shape.hidden:
            layers += [nn.Linear(width, size), nn.ReLU()]
            width = size
        self.body = nn.Sequential(*layers)
        self.head = head.build(width, shape.actions)

    def forward(self, kinematics: torch.Tensor) -> torch.Tensor:
        return self.head(self.body(kinematics.float()))
