"""The ego vector: the agent's own state as numbers, as Min et al.'s code adds scalars to its
LIDAR rays. A preset picks its fields from :data:`~overtake.protocol.vocabulary.EGO_FIELDS`
(``ego_vector.fields``): Min et al.'s are the authors' code's six, the left, right and forward
warnings (0 or 1), the distance to the car ahead and its speed, and the host's speed."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from overtake.protocol.vocabulary import EGO_FIELDS

from ..assist import DriverWarnings
from ..road import Road
from ..units import KMH
from ..validation import check, check_flag, check_range
from .base import Scene, SensorConfig, SensorFacts, SensorSpace

if TYPE_CHECKING:
    from ..config import SimConfig

# The largest speed (m/s) the space admits, and the most lanes a road may have (road.py).
MAX_SPEED_MPS = 100.0
MAX_LANES = 12


@dataclass(frozen=True, slots=True)
class EgoVectorConfig(SensorConfig):
    """The ``ego`` observation: the agent's own state, field by field."""

    OBSERVATION: ClassVar[str] = "ego"

    enabled: bool = True
    # The authors' code's six scalars, in their order (its observation 360-365).
    fields: tuple[str, ...] = (
        "left_warning",
        "right_warning",
        "forward_warning",
        "ahead_distance_m",
        "ahead_speed_mps",
        "speed_mps",
    )
    # The distance to the car ahead is clipped here, and reads this where there is none (the
    # authors' code normalises it by its sensor range; the LIDAR's 80 m, chosen here).
    ahead_range_m: float = 80.0

    def __post_init__(self) -> None:
        check_flag("ego_vector.enabled", self.enabled)
        check(
            len(self.fields) >= 1
            and len(set(self.fields)) == len(self.fields)
            and all(name in EGO_FIELDS for name in self.fields),
            "ego_vector.fields",
            self.fields,
            f"distinct names from {list(EGO_FIELDS)}, at least one",
        )
        check_range("ego_vector.ahead_range_m", self.ahead_range_m, 1.0, 1000.0)

    def build(self, config: SimConfig) -> EgoVector:
        return EgoVector(
            self,
            Road(config.road),
            config.ego.cruise_min_kmh * KMH,
            config.ego.cruise_max_kmh * KMH,
        )


Field = Callable[[Scene], np.ndarray]


class EgoVector:
    """(len(fields),) float32 per agent."""

    key = "ego"

    def __init__(
        self, config: EgoVectorConfig, road: Road, cruise_min_mps: float, cruise_max_mps: float
    ) -> None:
        self.fields = config.fields
        self.ahead_range_m = config.ahead_range_m
        self.road = road
        # Each field's bounds (the space) and how it is read from the scene (A, N).
        lanes = road.lane_count
        catalogue: dict[str, tuple[float, float, Field]] = {
            "speed_mps": (0.0, MAX_SPEED_MPS, lambda s: s.state.speed_mps[:, : s.agents]),
            "cruise_target_mps": (
                cruise_min_mps,
                cruise_max_mps,
                lambda s: s.state.desired_speed_mps[:, : s.agents],
            ),
            "lane_index": (0.0, lanes - 1, lambda s: road.lane_at(s.state.y_m[:, : s.agents])),
            "lane_count": (1.0, MAX_LANES, lambda s: np.full((s.arenas, s.agents), lanes)),
            "lane_change_progress": (0.0, 1.0, lambda s: s.state.change_progress[:, : s.agents]),
            "lane_change_direction": (
                -1.0,
                1.0,
                lambda s: s.state.target_lane[:, : s.agents] - s.state.lane[:, : s.agents],
            ),
            "left_warning": (0.0, 1.0, lambda s: s.warnings[..., DriverWarnings.LEFT]),
            "right_warning": (0.0, 1.0, lambda s: s.warnings[..., DriverWarnings.RIGHT]),
            "forward_warning": (0.0, 1.0, lambda s: s.warnings[..., DriverWarnings.FORWARD]),
            "ahead_distance_m": (
                0.0,
                self.ahead_range_m,
                lambda s: np.clip(s.ahead.gap_m, 0.0, self.ahead_range_m),
            ),
            "ahead_speed_mps": (0.0, MAX_SPEED_MPS, lambda s: s.ahead.speed_mps),
        }
        self._low = np.array([catalogue[f][0] for f in self.fields], dtype=np.float32)
        self._high = np.array([catalogue[f][1] for f in self.fields], dtype=np.float32)
        self._readers = [catalogue[f][2] for f in self.fields]

    def space(self) -> SensorSpace:
        return SensorSpace(
            (len(self.fields),), np.dtype(np.float32), self._low.copy(), self._high.copy()
        )

    def facts(self) -> SensorFacts:
        """Its fields by name; the car ahead is looked for up to ``ahead_range_m``."""
        return SensorFacts(columns=tuple(self.fields), ahead_m=self.ahead_range_m)

    def observe(self, scene: Scene) -> np.ndarray:
        out = np.empty((scene.arenas, scene.agents, len(self.fields)), dtype=np.float32)
        for i, read in enumerate(self._readers):
            out[..., i] = read(scene)
        return out
