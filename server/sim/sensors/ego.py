"""The ego vector: the agent's own state as numbers, as Min et al.'s code adds scalars to its
LIDAR rays. Its fields are :data:`~overtake.protocol.vocabulary.EGO_FIELDS`: speed (m/s),
cruise target (m/s), lane index (0 = rightmost), lane count, lane-change progress (0-1) and
direction (-1 right, 0, +1 left)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from overtake.protocol.vocabulary import EGO_FIELDS

from ..road import Road
from ..units import KMH
from ..validation import check_flag
from .base import Scene, SensorConfig, SensorSpace

if TYPE_CHECKING:
    from ..config import SimConfig

# The largest speed (m/s) the space admits, and the most lanes a road may have (road.py).
MAX_SPEED_MPS = 100.0
MAX_LANES = 12


@dataclass(frozen=True, slots=True)
class EgoVectorConfig(SensorConfig):
    """The ``ego`` observation: the agent's own speed, cruise target and lane."""

    enabled: bool = True

    def __post_init__(self) -> None:
        check_flag("ego_vector.enabled", self.enabled)

    def build(self, config: SimConfig) -> EgoVector:
        return EgoVector(
            Road(config.road), config.ego.cruise_min_kmh * KMH, config.ego.cruise_max_kmh * KMH
        )


class EgoVector:
    """(6,) float32 per agent, the fields of EGO_FIELDS."""

    key = "ego"

    def __init__(self, road: Road, cruise_min_mps: float, cruise_max_mps: float) -> None:
        self.road = road
        self.cruise_min_mps = cruise_min_mps
        self.cruise_max_mps = cruise_max_mps

    def space(self) -> SensorSpace:
        # The lane count's bounds are the configurable range, so no bound pair is degenerate.
        lanes = self.road.lane_count
        low = np.array([0.0, self.cruise_min_mps, 0.0, 1.0, 0.0, -1.0], dtype=np.float32)
        high = np.array(
            [MAX_SPEED_MPS, self.cruise_max_mps, lanes - 1, MAX_LANES, 1.0, 1.0], dtype=np.float32
        )
        return SensorSpace((len(EGO_FIELDS),), np.dtype(np.float32), low, high)

    def observe(self, scene: Scene) -> np.ndarray:
        st, n = scene.state, scene.agents
        out = np.empty((scene.arenas, n, len(EGO_FIELDS)), dtype=np.float32)
        out[..., 0] = st.speed_mps[:, :n]
        out[..., 1] = st.desired_speed_mps[:, :n]
        out[..., 2] = self.road.lane_at(st.y_m[:, :n])
        out[..., 3] = self.road.lane_count
        out[..., 4] = st.change_progress[:, :n]
        out[..., 5] = st.target_lane[:, :n] - st.lane[:, :n]
        return out
