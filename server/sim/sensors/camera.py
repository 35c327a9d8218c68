"""A front camera rendered in software: a pinhole view from the driver's seat, in numpy.

The ground is ray-cast per pixel once (the rays are fixed to the car), then shaded per frame by
where each ray meets the road: asphalt, lane markings (dashed between lanes, solid at the
edges), shoulder and grass, sky above the horizon. Cars are boxes ``VEHICLE_HEIGHT_M`` tall,
drawn as the screen rectangle that bounds their eight projected corners, so they grow as they
come closer. All cars share one colour, so their union is all that is needed. Projections are
numpy over all observers, the cars' projection and the per-pixel shading and filling compiled
loops (:mod:`..kernels`).

Image rows run top to bottom, columns left to right; (H, W) uint8 for grey, (H, W, 3) for RGB.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from ..road import RoadConfig
from ..validation import check, check_range
from .base import ObserverViews, Scene, SensorConfig, SensorFacts, SensorSpace
from .kernels import colour, paint_cars, paint_ground

if TYPE_CHECKING:
    from ..config import SimConfig

VEHICLE_HEIGHT_M = 1.5
LANE_LINE_WIDTH_M = 0.15
DASH_LENGTH_M = 6.0
DASH_PERIOD_M = 12.0
NEAR_PLANE_M = 0.3

# Surface classes and their colours (grey values follow ITU-R BT.601 luma of the RGB ones).
SKY, GRASS, SHOULDER, ROAD, MARKING, CAR = range(6)
_RGB = np.array(
    [
        [150, 190, 235],  # sky
        [70, 120, 60],  # grass
        [150, 150, 140],  # shoulder
        [90, 90, 95],  # asphalt
        [240, 240, 240],  # lane marking
        [200, 30, 30],  # car
    ],
    dtype=np.float64,
)
_GREY = np.round(_RGB @ np.array([0.299, 0.587, 0.114])).astype(np.uint8)
_GREY[CAR] = 20  # darker than the road in grey, so cars stand out against asphalt and sky


@dataclass(frozen=True, slots=True)
class CameraConfig(SensorConfig):
    """A front camera at the driver's seat, rendered in software (a pinhole perspective view)."""

    OBSERVATION: ClassVar[str] = "camera"

    enabled: bool = True
    # 80x80 grey, as the authors' code feeds its network (the paper gives no size).
    width_px: int = 80
    height_px: int = 80
    horizontal_fov_deg: float = 70.0
    rgb: bool = False
    mount_height_m: float = 1.2
    # Pitched down so that more of the image shows road than sky.
    pitch_down_deg: float = 6.0
    mount_forward_m: float = 0.3
    max_distance_m: float = 200.0

    def __post_init__(self) -> None:
        check(isinstance(self.enabled, bool), "camera.enabled", self.enabled, "true or false")
        check(isinstance(self.rgb, bool), "camera.rgb", self.rgb, "true or false")
        for name in ("width_px", "height_px"):
            value = getattr(self, name)
            check(
                isinstance(value, int) and 8 <= value <= 1024,
                f"camera.{name}",
                value,
                "an integer from 8 to 1024",
            )
        check_range("camera.horizontal_fov_deg", self.horizontal_fov_deg, 10.0, 160.0)
        check_range("camera.mount_height_m", self.mount_height_m, 0.3, 5.0)
        check_range("camera.pitch_down_deg", self.pitch_down_deg, -30.0, 45.0)
        check_range("camera.mount_forward_m", self.mount_forward_m, -5.0, 5.0)
        check_range("camera.max_distance_m", self.max_distance_m, 10.0, 2000.0)

    def build(self, config: SimConfig) -> Camera:
        return Camera(self, config.road)


class Camera:
    """The ``camera`` observation: (H, W) grey or (H, W, 3) RGB uint8 per agent."""

    key = "camera"

    def __init__(self, camera: CameraConfig, road: RoadConfig) -> None:
        self.config = camera
        self.height = camera.height_px
        self.width = camera.width_px
        self.focal_px = (camera.width_px / 2.0) / np.tan(
            np.radians(camera.horizontal_fov_deg) / 2.0
        )
        self.pitch = np.radians(camera.pitch_down_deg)
        self.lane_count = road.lane_count
        self.lane_width = road.lane_width_m
        self.road_right_y = 0.0
        self.road_left_y = road.lane_count * road.lane_width_m
        # Grey images are drawn in grey values directly; RGB ones as classes, then coloured.
        self._stage_value = np.arange(len(_GREY), dtype=np.uint8) if camera.rgb else _GREY
        self._rgb_palette = _RGB.astype(np.uint8)
        half_road = 0.5 * road.lane_count
        # paint_ground's edges (lane widths from the road's middle, float32 as the lanes are)
        # and surface values.
        self._edges = (
            np.float32(half_road),
            np.float32(half_road + road.barrier_offset_m * (1.0 / road.lane_width_m)),
            np.float32(half_road + 0.5),
            np.float32(half_road - 0.5),
            self._stage_value[[GRASS, SHOULDER, ROAD, MARKING]].copy(),
        )

        # Rows below the horizon see the ground at a depth that depends on the row alone (the
        # camera only pitches): t is the ray length to the ground per unit forward component.
        # Within a row the ground's lateral position is linear in the column, for any yaw, so
        # every surface boundary in a row is an interval of columns computed in closed form.
        v = (np.arange(self.height) + 0.5) - self.height / 2.0
        up = -v / self.focal_px
        cos_p, sin_p = np.cos(self.pitch), np.sin(self.pitch)
        ray_x = cos_p + up * sin_p
        ray_z = -sin_p + up * cos_p
        with np.errstate(divide="ignore"):
            t = np.where(ray_z < 0.0, camera.mount_height_m / -ray_z, np.inf)
        ahead = ray_x * np.where(np.isfinite(t), t, 0.0)
        ground_rows = np.flatnonzero(np.isfinite(t) & (ahead < camera.max_distance_m))
        self.first_ground_row = int(ground_rows[0]) if ground_rows.size else self.height
        rows = slice(self.first_ground_row, self.height)
        self.row_forward = ahead[rows]  # metres ahead of the eye where the row meets ground
        self.row_metres_per_px = t[rows] / self.focal_px  # sideways ground size of a pixel
        # Lines are widened to about a pixel so that they do not alias away in the distance;
        # dashes become solid where one row spans more ground than the gap between dashes.
        row_line_half_m = np.maximum(LANE_LINE_WIDTH_M / 2.0, 0.5 * self.row_metres_per_px)
        along = np.abs(np.diff(self.row_forward, prepend=self.row_forward[0] * 2.0))
        self.row_dash_solid = along > (DASH_PERIOD_M - DASH_LENGTH_M) / 2.0
        col_centres = (np.arange(self.width) + 0.5) - self.width / 2.0
        self._col_basis = np.stack([np.ones(self.width), col_centres]).astype(np.float32)
        # Per ground pixel (R, W), so that comparisons broadcast only over observers.
        self._row_line_half32 = np.repeat(
            (row_line_half_m / self.lane_width).astype(np.float32)[:, None], self.width, axis=1
        )
        self._cos_p, self._sin_p = np.cos(self.pitch), np.sin(self.pitch)
        self._corner_l = np.array([-1.0, 1.0, 1.0, -1.0])
        self._corner_w = np.array([-1.0, -1.0, 1.0, 1.0])
        # Height of a box's bottom and top corners relative to the camera.
        drop = np.array([0.0, VEHICLE_HEIGHT_M]) - camera.mount_height_m
        self._drop_sin = drop * self._sin_p  # (2,)
        self._drop_cos = drop * self._cos_p

    def _ground(
        self,
        eye_x: np.ndarray,
        eye_y: np.ndarray,
        cos_h: np.ndarray,
        sin_h: np.ndarray,
        road_x: np.ndarray,
    ) -> np.ndarray:
        """(O, H, W) uint8 sky and ground: grey values, or surface classes for RGB."""
        value = self._stage_value
        observers = eye_x.shape[0]
        image = np.full((observers, self.height, self.width), value[SKY], dtype=np.uint8)
        if self.first_ground_row >= self.height:
            return image
        # Ground position of row r at column centre c, in lane widths from the right road
        # edge: base + slope * c (linear within a row for any yaw).
        inv_w = 1.0 / self.lane_width
        base = ((eye_y[:, None] + sin_h[:, None] * self.row_forward) * inv_w).astype(np.float32)
        slope = (-cos_h[:, None] * self.row_metres_per_px * inv_w).astype(np.float32)
        # One small matrix product instead of a broadcast with an 84-long inner loop.
        pair = np.empty(base.shape + (2,), dtype=np.float32)
        pair[..., 0], pair[..., 1] = base, slope
        lanes = np.matmul(pair, self._col_basis)  # (O, R, W)
        # Which rows meet the road between two dashes: inner lines are dashed by where the row
        # meets the road along the camera's axis (during a lane change far lanes' dashes shift
        # by a metre or two); the edge lines are solid.
        world_x = (road_x + eye_x)[:, None] + cos_h[:, None] * self.row_forward
        gap = ~(self.row_dash_solid | ((world_x % DASH_PERIOD_M) < DASH_LENGTH_M))  # (O, R)
        # Road within L/2 lane widths of the middle, shoulder to the rails, grass beyond; lane
        # lines where a pixel is within a line's half width of the nearest line on the road.
        paint_ground(image, self.first_ground_row, lanes, self._row_line_half32, gap, *self._edges)
        return image

    @property
    def shape(self) -> tuple[int, ...]:
        return (self.height, self.width, 3) if self.config.rgb else (self.height, self.width)

    def space(self) -> SensorSpace:
        return SensorSpace.uniform(self.shape, np.uint8, 0, 255)

    def facts(self) -> SensorFacts:
        """A view ahead that draws nothing beyond ``max_distance_m``."""
        return SensorFacts(ahead_m=self.config.max_distance_m)

    def observe(self, scene: Scene) -> np.ndarray:
        road_x = np.repeat(scene.state.x_m[:, 0], scene.agents)
        image = self.render(scene.views, road_x)
        return image.reshape((scene.arenas, scene.agents) + image.shape[1:])

    def render(self, views: ObserverViews, road_x: np.ndarray) -> np.ndarray:
        """Images (O, H, W[, 3]) uint8 for the O observers of ``views``, at the driver's seat of
        their car, each seeing its ``car_visible`` cars. The views' x values are relative to a
        reference at ``road_x`` (O,) along the road, which places the dashes."""
        cam_x, cam_y, heading = views.origin_x, views.origin_y, views.heading
        mount = self.config.mount_forward_m
        cos_h = np.cos(heading)
        sin_h = np.sin(heading)
        eye_x = cam_x + mount * cos_h
        eye_y = cam_y + mount * sin_h

        surface = self._ground(eye_x, eye_y, cos_h, sin_h, road_x)

        # Cars: the screen rectangle bounding each box's eight corners, painted over the
        # ground, car by car in one compiled loop.
        paint_cars(
            surface,
            eye_x,
            eye_y,
            cos_h,
            sin_h,
            views.car_x,
            views.car_y,
            views.car_half_length,
            views.car_half_width,
            views.car_visible,
            self._corner_l,
            self._corner_w,
            self._cos_p,
            self._sin_p,
            self._drop_sin,
            self._drop_cos,
            self.focal_px,
            NEAR_PLANE_M,
            self.config.max_distance_m,
            self._stage_value[CAR],
        )
        image = surface
        return colour(image, self._rgb_palette) if self.config.rgb else image
