"""A 360-degree LIDAR, vectorised over observers, vehicles and only the rays each vehicle covers.

Ray ``r`` of ``R`` leaves the observer's centre at heading + r * 360/R degrees, counter-clockwise
(to the left, seen from above): index 0 is straight ahead, R/4 left, R/2 behind, 3R/4 right.
Vehicles are axis-aligned rectangles on the road; the guard rails are two lines parallel to it.

The naive test of every ray against every car costs O(R * V) per observer. A car covers only a
few degrees of the scan, so each car's angular extent is computed first and only the rays inside
it are intersected with its box, in a compiled loop (:func:`.kernels.lidar_scan`; the bearings
come from numpy's arctan2).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from ..road import Road
from ..validation import check, check_range
from .base import ObserverViews, Scene, SensorConfig, SensorFacts, SensorSpace
from .kernels import lidar_scan

if TYPE_CHECKING:
    from ..config import SimConfig

TWO_PI = 2.0 * np.pi


@dataclass(frozen=True, slots=True)
class LidarConfig(SensorConfig):
    """A 360-degree LIDAR at the car's centre.

    Ray i points i * (360 / ray_count) degrees counter-clockwise (to the left, seen from above)
    from straight ahead: with 360 rays, index 0 is straight ahead, 90 is left, 180 is behind and
    270 is right. Values are metres, clipped at ``max_range_m``.
    """

    OBSERVATION: ClassVar[str] = "lidar"

    enabled: bool = True
    ray_count: int = 360
    max_range_m: float = 80.0

    def __post_init__(self) -> None:
        check(isinstance(self.enabled, bool), "lidar.enabled", self.enabled, "true or false")
        check(
            isinstance(self.ray_count, int) and 4 <= self.ray_count <= 3600,
            "lidar.ray_count",
            self.ray_count,
            "an integer from 4 to 3600",
        )
        check_range("lidar.max_range_m", self.max_range_m, 1.0, 1000.0)

    def build(self, config: SimConfig) -> Lidar:
        road = Road(config.road)
        return Lidar(self.ray_count, self.max_range_m, road.rail_left_y_m, road.rail_right_y_m)


class Lidar:
    """The ``lidar`` observation: (rays,) float32 distances (m) per agent."""

    key = "lidar"

    def __init__(
        self, ray_count: int, max_range_m: float, rail_left_y_m: float, rail_right_y_m: float
    ) -> None:
        self.ray_count = ray_count
        self.max_range_m = max_range_m
        self.rail_left_y_m = rail_left_y_m
        self.rail_right_y_m = rail_right_y_m
        self.step_rad = TWO_PI / ray_count
        angles = np.arange(ray_count) * self.step_rad
        self._cos = np.cos(angles)
        self._sin = np.sin(angles)
        self._corner_l = np.array([-1.0, 1.0, 1.0, -1.0])
        self._corner_w = np.array([-1.0, -1.0, 1.0, 1.0])

    def space(self) -> SensorSpace:
        return SensorSpace.uniform((self.ray_count,), np.float32, 0.0, self.max_range_m)

    def facts(self) -> SensorFacts:
        """Rays all around, one per ``360 / ray_count`` degrees, up to the range."""
        return SensorFacts(range_m=self.max_range_m)

    def observe(self, scene: Scene) -> np.ndarray:
        return self.scan(scene.views).reshape(scene.arenas, scene.agents, -1)

    def scan(self, views: ObserverViews) -> np.ndarray:
        """Distances (O, R) float32 in metres, clipped at the maximum range, for the O observers
        of ``views`` (each sees its ``car_visible`` cars and both guard rails)."""
        origin_x, origin_y, heading = views.origin_x, views.origin_y, views.heading
        car_x, car_y = views.car_x, views.car_y
        car_half_length, car_half_width = views.car_half_length, views.car_half_width
        rel_x = car_x - origin_x[:, None]
        rel_y = car_y - origin_y[:, None]
        corner_x = rel_x[..., None] + car_half_length[..., None] * self._corner_l
        corner_y = rel_y[..., None] + car_half_width[..., None] * self._corner_w
        dist = np.empty((origin_x.shape[0], self.ray_count), dtype=np.float32)
        lidar_scan(
            origin_x,
            origin_y,
            heading,
            np.cos(heading),
            np.sin(heading),
            rel_x,
            rel_y,
            np.broadcast_to(car_half_length, rel_x.shape),
            np.broadcast_to(car_half_width, rel_x.shape),
            np.broadcast_to(views.car_visible, rel_x.shape),
            np.arctan2(rel_y, rel_x),
            np.arctan2(corner_y, corner_x),
            self._cos,
            self._sin,
            self.rail_left_y_m,
            self.rail_right_y_m,
            self.max_range_m,
            dist,
        )
        return dist
