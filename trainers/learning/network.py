"""The multi-modal Q-network of Min et al. (Table II), with camera-only and LIDAR-only variants.

- camera: the last ``stack`` grey frames, channels first, through the DQN convolutions
  (8x8 stride 4, 32; 4x4 stride 2, 64; 3x3 stride 1, 64), ReLU after each;
- LIDAR: the last ``stack`` scans through an LSTM with 256 cells (its last output is the
  feature);
- the ego vector of the latest decision is concatenated too, whatever fields the environment
  gives: Min et al.'s six (three warnings, the car ahead's distance and speed, the car's
  speed), which the authors' code feeds beside the LIDAR, for the LIDAR and multi-modal
  networks; the car's speed alone for the camera-only one (:func:`ego_fields_read`), so that
  each variant sees other cars only through its own sensors;
- the concatenation goes through a 512-unit layer with ReLU, then the head a
  :class:`~.heads.HeadSpec` names (plain Q-values, Min et al.'s dueling streams of Eq. 9, or
  QR-DQN's quantiles: :mod:`.heads`).

Inputs arrive as stored (camera uint8, LIDAR metres, ego in its own units) and are scaled here
by the observation space's bounds, so the replay keeps the compact dtypes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch
from torch import nn

from .heads import PLAIN, HeadSpec

Inputs = Literal["camera", "lidar", "both", "grid", "camera-map", "kinematics"]
# The sensors each input configuration reads stacked over the last frames: Min et al.'s camera
# and LIDAR, Ho's occupancy grid (:mod:`.grid_network`), or Fayjie et al.'s camera and LIDAR
# map (:mod:`.two_stream_network`) ...
INPUT_SENSORS: dict[str, tuple[str, ...]] = {
    "camera": ("camera",),
    "lidar": ("lidar",),
    "both": ("camera", "lidar"),
    "grid": ("grid",),
    "camera-map": ("camera", "lidar_map"),
    "kinematics": ("kinematics",),
}
# ... and those it reads at the latest decision only: the ego vector for Min et al.'s networks,
# the action stack (itself the last four actions) for Ho's.
LATEST_SENSORS: dict[str, tuple[str, ...]] = {
    "camera": ("ego",),
    "lidar": ("ego",),
    "both": ("ego",),
    "grid": ("actions",),
    "camera-map": (),
    "kinematics": (),
}
INPUTS: tuple[str, ...] = tuple(INPUT_SENSORS)


# ... and the ego vector's fields it reads where not the preset's: the camera-only network
# sees the car's own speed alone, since the warnings and the car ahead's distance and speed
# ride with the LIDAR in the authors' code (its vector's elements 360-365), so that it sees
# other cars only through its camera (Min et al.'s ablation).
EGO_FIELDS_READ: dict[str, tuple[str, ...]] = {"camera": ("speed_mps",)}


def observations_read(inputs: str) -> tuple[str, ...]:
    """Every observation a network of ``inputs`` reads: what a trainer asks the simulator
    for (OpenRequest.observations), so that no sensor it ignores is rendered."""
    return (*LATEST_SENSORS[inputs], *INPUT_SENSORS[inputs])


def ego_fields_read(inputs: str) -> tuple[str, ...]:
    """The ego vector's fields a network of ``inputs`` reads, which a trainer asks the
    simulator for (OpenRequest.ego_fields); none: the preset's."""
    return EGO_FIELDS_READ.get(inputs, ())


@dataclass(frozen=True)
class NetworkShape:
    """What the network is built for: the single observation's shapes and the action count."""

    camera_hw: tuple[int, int]
    lidar_rays: int
    ego_size: int
    actions: int
    stack: int = 4
    lidar_max_m: float = 80.0
    ego_high: tuple[float, ...] = ()

    @classmethod
    def from_space(cls, space, actions: int, stack: int) -> NetworkShape:
        """From a single environment's Dict observation space."""
        camera = space["camera"].shape if "camera" in space.spaces else (84, 84)
        lidar = space["lidar"] if "lidar" in space.spaces else None
        ego = space["ego"]
        high = np.maximum(np.abs(ego.high), np.abs(ego.low))
        return cls(
            camera_hw=(int(camera[0]), int(camera[1])),
            lidar_rays=int(lidar.shape[0]) if lidar is not None else 0,
            ego_size=int(ego.shape[0]),
            actions=actions,
            stack=stack,
            lidar_max_m=float(lidar.high.max()) if lidar is not None else 1.0,
            ego_high=tuple(float(h) if h > 0 else 1.0 for h in high),
        )


def conv_output_size(height: int, width: int) -> int:
    """Features out of the three DQN convolutions for a ``height`` x ``width`` image."""
    for kernel, stride in ((8, 4), (4, 2), (3, 1)):
        height = (height - kernel) // stride + 1
        width = (width - kernel) // stride + 1
    if height < 1 or width < 1:
        raise ValueError(
            "the camera image is too small for the DQN convolutions (at least 36x36 pixels)"
        )
    return 64 * height * width


class QNetwork(nn.Module):
    """The head's output (Q-values (B, actions), or quantiles) from stacked camera (B, S, H, W)
    uint8, LIDAR (B, S, R) and ego (B, E)."""

    ego_scale: torch.Tensor  # a buffer: 1 / each ego field's upper bound
    # The observations forward() takes, in order (None for one the inputs leave out).
    input_names: tuple[str, ...] = ("camera", "lidar", "ego")

    def __init__(
        self,
        shape: NetworkShape,
        inputs: Inputs = "both",
        head: HeadSpec = PLAIN,
        lstm_cells: int = 256,
        hidden: int = 512,
    ) -> None:
        super().__init__()
        if inputs not in ("camera", "lidar", "both"):
            raise ValueError(
                f"Min et al.'s network reads camera, lidar or both, got inputs={inputs!r}"
            )
        if inputs in ("lidar", "both") and shape.lidar_rays == 0:
            raise ValueError(f"inputs={inputs!r} needs the LIDAR, but the environment has none")
        self.shape, self.inputs = shape, inputs
        self.uses_camera = "camera" in INPUT_SENSORS[inputs]
        self.uses_lidar = "lidar" in INPUT_SENSORS[inputs]
        self.used_inputs = ("ego", *INPUT_SENSORS[inputs])
        features = shape.ego_size
        if self.uses_camera:
            self.conv = nn.Sequential(
                nn.Conv2d(shape.stack, 32, kernel_size=8, stride=4),
                nn.ReLU(),
                nn.Conv2d(32, 64, kernel_size=4, stride=2),
                nn.ReLU(),
                nn.Conv2d(64, 64, kernel_size=3, stride=1),
                nn.ReLU(),
                nn.Flatten(),
            )
            features += conv_output_size(*shape.camera_hw)
        if self.uses_lidar:
            self.lstm = nn.LSTM(shape.lidar_rays, lstm_cells, batch_first=True)
            features += lstm_cells
        self.fuse = nn.Sequential(nn.Linear(features, hidden), nn.ReLU())
        self.head = head.build(hidden, shape.actions)
        self.register_buffer(
            "ego_scale",
            torch.tensor(
                [1.0 / h for h in (shape.ego_high or (1.0,) * shape.ego_size)], dtype=torch.float32
            ),
        )

    def forward(
        self, camera: torch.Tensor | None, lidar: torch.Tensor | None, ego: torch.Tensor
    ) -> torch.Tensor:
        parts = [ego.float() * self.ego_scale]
        if self.uses_camera:
            assert camera is not None
            parts.append(self.conv(camera.float() / 255.0))
        if self.uses_lidar:
            assert lidar is not None
            out, _ = self.lstm(lidar.float() / self.shape.lidar_max_m)
            parts.append(out[:, -1])
        return self.head(self.fuse(torch.cat(parts, dim=1)))
