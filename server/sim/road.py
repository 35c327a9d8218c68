"""The road: a straight highway of parallel lanes between two guard rails.

Lanes are numbered from the right (0 = rightmost); x runs along the road, y across it from the
right road edge, +y to the driver's left. The rails stand ``barrier_offset_m`` outside the
outer lane edges; the LIDAR sees them and the camera draws them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .validation import check, check_range


@dataclass(frozen=True, slots=True)
class RoadConfig:
    """A straight highway. Lanes are numbered from the right (0 = rightmost); +y points left."""

    lane_count: int = 5
    lane_width_m: float = 3.5
    # Guard rails stand this far outside the outer lane edges; the LIDAR sees them.
    barrier_offset_m: float = 1.0

    def __post_init__(self) -> None:
        check(
            isinstance(self.lane_count, int) and 1 <= self.lane_count <= 12,
            "road.lane_count",
            self.lane_count,
            "an integer from 1 to 12",
        )
        check_range("road.lane_width_m", self.lane_width_m, 2.5, 6.0)
        check_range("road.barrier_offset_m", self.barrier_offset_m, 0.0, 10.0)


class Road:
    """The geometry every other part reads: lanes, their centres, the rails."""

    def __init__(self, config: RoadConfig) -> None:
        self.config = config
        self.lane_count = config.lane_count
        self.lane_width_m = config.lane_width_m
        self.rail_left_y_m = config.lane_count * config.lane_width_m + config.barrier_offset_m
        self.rail_right_y_m = -config.barrier_offset_m

    def centre_y(self, lane: np.ndarray) -> np.ndarray:
        """The y (m) of the middle of ``lane``."""
        return (lane + 0.5) * self.lane_width_m

    def lane_at(self, y_m: np.ndarray) -> np.ndarray:
        """The lane (as float64) whose strip holds ``y_m``, clipped to the road's lanes."""
        return np.minimum(np.maximum(np.floor(y_m / self.lane_width_m), 0.0), self.lane_count - 1)
