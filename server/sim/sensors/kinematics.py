"""highway-env's Kinematics observation (``envs/common/observation.py``, KinematicObservation),
for every preset: a table of the car and the cars nearest it, a row each, a column per
feature.

The first row is the observing car itself, in absolute coordinates; then up to
``vehicles_count - 1`` other cars within 200 m (highway-env's PERCEPTION_DISTANCE, five times
its maximum speed), nearest along the road first, and none more than two car lengths behind
unless ``see_behind``; relative to the observer's x, y, vx and vy unless ``absolute``. Rows
without a car are zeros. Normalised features are mapped from their range to [-1, 1] and, with
``clip``, clipped there; the default ranges are highway-env's: x +-200 m, y +- the road's
width, vx and vy +-80 m/s.

Coordinates are highway-env's, whatever the preset: x along the road, y across it from the
centre of the leftmost lane, growing to the right, headings positive to the right (the
simulator's own y grows to the left): a policy trained on highway-env reads the same numbers.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from ..validation import check, check_flag
from .base import Scene, SensorConfig, SensorFacts, SensorSpace
from .kernels import PERCEPTION_M, observe_kinematics

if TYPE_CHECKING:
    from ..config import SimConfig

# highway-env's feature names (kinematics.py, Vehicle.to_dict), in the columns' code order.
FEATURES = (
    "presence",
    "x",
    "y",
    "vx",
    "vy",
    "heading",
    "cos_h",
    "sin_h",
    "cos_d",
    "sin_d",
    "long_off",
    "lat_off",
    "ang_off",
)
_UNBOUNDED = float(np.finfo(np.float32).max)


@dataclass(frozen=True, slots=True)
class KinematicsConfig(SensorConfig):
    """The ``kinematics`` observation (highway-env's defaults: 5 cars, presence, x, y, vx,
    vy, relative, normalised, clipped, nobody behind)."""

    OBSERVATION: ClassVar[str] = "kinematics"

    enabled: bool = False
    vehicles_count: int = 5
    features: tuple[str, ...] = ("presence", "x", "y", "vx", "vy")
    # Normalisation ranges; y's None: +- the road's width (highway-env: its lane width times
    # the lanes).
    x_range_m: tuple[float, float] = (-200.0, 200.0)
    y_range_m: tuple[float, float] | None = None
    vx_range_mps: tuple[float, float] = (-80.0, 80.0)
    vy_range_mps: tuple[float, float] = (-80.0, 80.0)
    absolute: bool = False
    normalize: bool = True
    clip: bool = True
    see_behind: bool = False

    def __post_init__(self) -> None:
        check_flag("kinematics.enabled", self.enabled)
        check(
            isinstance(self.vehicles_count, int) and 1 <= self.vehicles_count <= 100,
            "kinematics.vehicles_count",
            self.vehicles_count,
            "an integer from 1 to 100",
        )
        check(
            len(self.features) >= 1
            and len(set(self.features)) == len(self.features)
            and all(name in FEATURES for name in self.features),
            "kinematics.features",
            self.features,
            f"distinct names from {list(FEATURES)}, at least one",
        )
        for name in ("x_range_m", "y_range_m", "vx_range_mps", "vy_range_mps"):
            value = getattr(self, name)
            if value is not None:
                check(
                    len(value) == 2 and value[0] < value[1] and all(map(math.isfinite, value)),
                    f"kinematics.{name}",
                    value,
                    "a pair (low, high) with low < high",
                )
        for name in ("absolute", "normalize", "clip", "see_behind"):
            check_flag(f"kinematics.{name}", getattr(self, name))

    def build(self, config: SimConfig) -> Kinematics:
        return Kinematics(self, config)


class Kinematics:
    """(vehicles_count, len(features)) float32 per agent."""

    key = "kinematics"

    def __init__(self, config: KinematicsConfig, sim_config: SimConfig) -> None:
        self.config = config
        road = sim_config.road
        self.lanes, self.lane_width = road.lane_count, road.lane_width_m
        self.length = sim_config.ego.length_m
        width = self.lane_width * self.lanes
        y_range = config.y_range_m or (-width, width)
        self.codes = np.array([FEATURES.index(f) for f in config.features], dtype=np.int64)
        # Per feature code: whether it is normalised, and its range.
        ranges = {1: config.x_range_m, 2: y_range, 3: config.vx_range_mps, 4: config.vy_range_mps}
        self.low = np.zeros(len(FEATURES))
        self.high = np.ones(len(FEATURES))
        self.scaled = np.zeros(len(FEATURES), dtype=bool)
        for code, (low, high) in ranges.items():
            self.low[code], self.high[code] = low, high
            self.scaled[code] = config.normalize

    def space(self) -> SensorSpace:
        shape = (self.config.vehicles_count, len(self.codes))
        low = np.empty(shape, dtype=np.float32)
        high = np.empty(shape, dtype=np.float32)
        for column, code in enumerate(self.codes):
            bounded = FEATURES[code] in ("cos_h", "sin_h", "cos_d", "sin_d")
            if code == 0:
                bounds = (0.0, 1.0)
            elif (self.scaled[code] and self.config.clip) or bounded:
                bounds = (-1.0, 1.0)
            else:
                bounds = (-_UNBOUNDED, _UNBOUNDED)
            low[:, column], high[:, column] = bounds
        return SensorSpace(shape, np.dtype(np.float32), low, high)

    def facts(self) -> SensorFacts:
        """Its features by name and the ranges of those normalised; it sees 200 m around, two
        car lengths behind at most unless it sees behind."""
        behind = PERCEPTION_M if self.config.see_behind else 2 * self.length
        scales = tuple(
            (FEATURES[code], float(self.low[code]), float(self.high[code]))
            for code in self.codes
            if self.scaled[code]
        )
        return SensorFacts(
            columns=tuple(self.config.features), ahead_m=PERCEPTION_M, behind_m=behind,
            side_m=PERCEPTION_M, range_m=PERCEPTION_M, scales=scales,
        )  # fmt: skip

    def observe(self, scene: Scene) -> np.ndarray:
        st, config = scene.state, self.config
        out = np.zeros(
            (scene.arenas, scene.agents, config.vehicles_count, len(self.codes)), np.float32
        )
        observe_kinematics(
            st.x_m, st.y_m, st.speed_mps, scene.headings, st.active, scene.agents,
            self.lanes, self.lane_width, self.length, self.codes, self.scaled, self.low,
            self.high, config.clip, config.absolute, config.see_behind, out,
        )  # fmt: skip
        return out
