"""Fayjie et al.'s LIDAR as a grid map (2018, §III.A and Fig. 8): the scan's returns drawn into
a bird's-eye image of the area ahead of the car.

The map is ``cells`` by ``cells`` cells in the car's frame (square ones with the defaults):
rows from ``ahead_m`` ahead (row 0) to ``behind_m`` behind (the last row), columns from
``half_width_m`` to the left (column 0) to as far to the right. A cell is 255 where some ray of
the scan (the ``lidar`` section's rays and range, whether or not the ``lidar`` observation is
on) ends on a car or a guard rail inside it, and 0 elsewhere. The paper gives neither the
extent nor the resolution: 40 m ahead and 20 m either side (0.5 m cells) are chosen here, the
range of a car's reaction at highway speed and the whole width of a 5-lane road.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from ..validation import check, check_flag, check_range
from .base import Scene, SensorConfig, SensorFacts, SensorSpace
from .kernels import lidar_grid
from .lidar import Lidar

if TYPE_CHECKING:
    from ..config import SimConfig


@dataclass(frozen=True, slots=True)
class LidarMapConfig(SensorConfig):
    """The ``lidar_map`` observation: (cells, cells) uint8 per agent."""

    OBSERVATION: ClassVar[str] = "lidar_map"

    enabled: bool = False
    cells: int = 80
    ahead_m: float = 40.0
    behind_m: float = 0.0
    half_width_m: float = 20.0

    def __post_init__(self) -> None:
        check_flag("lidar_map.enabled", self.enabled)
        check(
            isinstance(self.cells, int) and 4 <= self.cells <= 512,
            "lidar_map.cells",
            self.cells,
            "an integer from 4 to 512",
        )
        check_range("lidar_map.ahead_m", self.ahead_m, 0.0, 500.0)
        check_range("lidar_map.behind_m", self.behind_m, 0.0, 500.0)
        check(
            self.ahead_m + self.behind_m > 0.0,
            "lidar_map.ahead_m + lidar_map.behind_m",
            self.ahead_m + self.behind_m,
            "a positive length",
        )
        check_range("lidar_map.half_width_m", self.half_width_m, 0.0, 500.0, low_open=True)

    def build(self, config: SimConfig) -> LidarMap:
        return LidarMap(self, config.lidar.build(config))


class LidarMap:
    """The ``lidar_map`` observation, for every agent at once."""

    key = "lidar_map"

    def __init__(self, config: LidarMapConfig, scanner: Lidar) -> None:
        self.cells = config.cells
        self.ahead_m = config.ahead_m
        self.behind_m = config.behind_m
        self.half_width_m = config.half_width_m
        self.row_m = (config.ahead_m + config.behind_m) / config.cells
        self.column_m = 2.0 * config.half_width_m / config.cells
        self.scanner = scanner
        angles = np.arange(scanner.ray_count) * scanner.step_rad
        self._cos, self._sin = np.cos(angles), np.sin(angles)

    def space(self) -> SensorSpace:
        return SensorSpace.uniform((self.cells, self.cells), np.uint8, 0, 255)

    def facts(self) -> SensorFacts:
        """Rows from ``ahead_m`` ahead to ``behind_m`` behind, columns ``half_width_m`` to
        either side."""
        return SensorFacts(ahead_m=self.ahead_m, behind_m=self.behind_m, side_m=self.half_width_m)

    def observe(self, scene: Scene) -> np.ndarray:
        distance = self.scanner.scan(scene.views)  # (O, R), in the car's frame
        image = lidar_grid(
            distance,
            self._cos,
            self._sin,
            self.scanner.max_range_m - 1e-3,
            self.ahead_m,
            self.half_width_m,
            self.row_m,
            self.column_m,
            self.cells,
        )
        return image.reshape(scene.arenas, scene.agents, self.cells, self.cells)
