"""Fayjie et al.'s two-stream Q-network (2018, §III.A and Fig. 1): the front camera and the
LIDAR map, each through convolutions with pooling, fused, then dense layers.

The paper gives the structure, not the sizes: "3 convolutional layers and 4 dense layers", one
stream per input (4 stacked RGB 80x80 camera frames, 4 stacked 80x80 LIDAR maps), "fused using
a flatten layer, preceded by a dense layer and a pooling layer for each data type". Chosen here,
sized for a CPU: per stream a convolution of 32 filters 5x5 with stride 2, then 64 3x3 and 64
3x3, each followed by ReLU and a 2x2 max pooling, flattened into a dense layer of 256 (ReLU);
the two streams concatenated through dense layers of 256 and 128 (ReLU) to the head a
:class:`~.heads.HeadSpec` names (plain Q-values by default, :mod:`.heads`). That is 3
convolutions per stream and 4 dense layers on each input's path. Inputs arrive as uint8 and are
scaled to [0, 1].
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from .heads import PLAIN, HeadSpec


@dataclass(frozen=True)
class TwoStreamShape:
    """What the network is built for: the camera's (height, width, channels), the map's
    (height, width), the action count and the frames stacked per observation."""

    camera_hwc: tuple[int, int, int]
    map_hw: tuple[int, int]
    actions: int
    stack: int = 4

    @classmethod
    def from_space(cls, space, actions: int, stack: int) -> TwoStreamShape:
        camera = space["camera"].shape
        channels = int(camera[2]) if len(camera) == 3 else 1
        lidar_map = space["lidar_map"].shape
        return cls(
            camera_hwc=(int(camera[0]), int(camera[1]), channels),
            map_hw=(int(lidar_map[0]), int(lidar_map[1])),
            actions=actions,
            stack=stack,
        )


def _stream(channels: int, height: int, width: int) -> tuple[nn.Sequential, int]:
    """A stream's convolutions and its dense layer, and the dense layer's width."""
    layers: list[nn.Module] = []
    for out, kernel, stride in ((32, 5, 2), (64, 3, 1), (64, 3, 1)):
        layers += [
            nn.Conv2d(channels, out, kernel_size=kernel, stride=stride, padding=kernel // 2),
            nn.ReLU(),
            nn.MaxPool2d(2, stride=2, ceil_mode=True),
        ]
        channels = out
        height = (height + 2 * (kernel // 2) - kernel) // stride + 1
        width = (width + 2 * (kernel // 2) - kernel) // stride + 1
        height, width = (height + 1) // 2, (width + 1) // 2
    if height < 1 or width < 1:
        raise ValueError("the image is too small for the two-stream convolutions")
    layers += [nn.Flatten(), nn.Linear(channels * height * width, 256), nn.ReLU()]
    return nn.Sequential(*layers), 256


def _channels_last(images: torch.Tensor) -> torch.Tensor:
    return images.contiguous(memory_format=torch.channels_last)


class TwoStreamQNetwork(nn.Module):
    """The head's output from stacked camera frames (B, S, H, W[, C]) and LIDAR maps
    (B, S, H, W), uint8."""

    # The observations forward() takes, in order.
    input_names: tuple[str, ...] = ("camera", "lidar_map")
    used_inputs: tuple[str, ...] = ("camera", "lidar_map")

    def __init__(self, shape: TwoStreamShape, head: HeadSpec = PLAIN) -> None:
        super().__init__()
        self.shape = shape
        height, width, channels = shape.camera_hwc
        self.camera, camera_out = _stream(shape.stack * channels, height, width)
        self.lidar_map, map_out = _stream(shape.stack, *shape.map_hw)
        self.fuse = nn.Sequential(
            nn.Linear(camera_out + map_out, 256), nn.ReLU(), nn.Linear(256, 128), nn.ReLU()
        )
        self.head = head.build(128, shape.actions)
        # Whether forward() hands the streams channels-last images (members' stacked streams
        # lay out their own input: overtake.trainers.learning.member_network.stacked_network).
        self.channels_last = True

    def forward(self, camera: torch.Tensor, lidar_map: torch.Tensor) -> torch.Tensor:
        if camera.dim() == 5:  # (B, S, H, W, C) -> (B, S * C, H, W)
            batch, stack, height, width, channels = camera.shape
            camera = camera.permute(0, 1, 4, 2, 3).reshape(batch, stack * channels, height, width)
        # The convolutions and poolings in the channels-last layout, where PyTorch's CPU max
        # pooling is several times faster: a lone update 250 -> 180 ms (issue 66).
        camera, lidar_map = camera.float() / 255.0, lidar_map.float() / 255.0
        if self.channels_last:
            camera, lidar_map = _channels_last(camera), _channels_last(lidar_map)
        features = torch.cat([self.camera(camera), self.lidar_map(lidar_map)], dim=1)
        return self.head(self.fuse(features))
