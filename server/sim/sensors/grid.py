"""Ho's occupancy grid (2018, §5 and §6.1): the cells around the agent that a vehicle covers.

The grid is ``cells`` rows along the road by ``1 + 2 * side_lanes`` lanes (Ho: 36 by 3, the
agent's lane and one either side), from ``ahead_m`` ahead of the agent's centre (row 0) to
``behind_m`` behind it (the last row), each row ``(ahead_m + behind_m) / cells`` long. Columns
go from the leftmost lane to the rightmost (Ho's left to right, as his screen shows them): with
one side lane, column 0 is the lane to the left, 1 the agent's own, 2 the lane to the right.

A cell holds 1 where some other vehicle's body covers part of it (``covered_by = "any_part"``),
or where its near edge lies under a body (``"near_edge"``, Ho's code, ``car.py``'s
``get_vision``: a car marks as many cells as it is long, from the one that holds its front
bumper), in its lane or in the lane it is moving into (a car changing lanes occupies both, as in
Ho's code), and 0 where none does; the agent itself is not an obstacle. Cells of lanes beyond
the road's edges hold ``off_road_value`` (-1 in Ho's code, which pads its view with -1 there; 0
makes the grid purely Boolean, as the thesis words it).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, ClassVar, Literal

import numpy as np

from ..validation import check, check_flag, check_range
from .base import Scene, SensorConfig, SensorFacts, SensorSpace

if TYPE_CHECKING:
    from ..config import SimConfig


@dataclass(frozen=True, slots=True)
class OccupancyGridConfig(SensorConfig):
    """The ``grid`` observation: (cells, lanes) int8 per agent."""

    OBSERVATION: ClassVar[str] = "grid"

    enabled: bool = False
    ahead_m: float = 20.0
    behind_m: float = 10.0
    cells: int = 36
    side_lanes: int = 1
    off_road_value: int = -1
    covered_by: Literal["any_part", "near_edge"] = "any_part"

    def __post_init__(self) -> None:
        check_flag("grid.enabled", self.enabled)
        check_range("grid.ahead_m", self.ahead_m, 0.0, 500.0)
        check_range("grid.behind_m", self.behind_m, 0.0, 500.0)
        check(
            self.ahead_m + self.behind_m > 0,
            "grid.ahead_m + grid.behind_m",
            self.ahead_m + self.behind_m,
            "a positive length",
        )
        check(
            isinstance(self.cells, int) and 1 <= self.cells <= 1000,
            "grid.cells",
            self.cells,
            "an integer from 1 to 1000",
        )
        check(
            isinstance(self.side_lanes, int) and 0 <= self.side_lanes <= 6,
            "grid.side_lanes",
            self.side_lanes,
            "an integer from 0 to 6",
        )
        check(
            self.off_road_value in (-1, 0, 1),
            "grid.off_road_value",
            self.off_road_value,
            "-1, 0 or 1",
        )
        check(
            self.covered_by in ("any_part", "near_edge"),
            "grid.covered_by",
            self.covered_by,
            "any_part or near_edge",
        )

    def build(self, config: SimConfig) -> OccupancyGrid:
        return OccupancyGrid(self, config.road.lane_count)


class OccupancyGrid:
    """The ``grid`` observation, for every agent at once."""

    key = "grid"

    def __init__(self, config: OccupancyGridConfig, lane_count: int) -> None:
        self.cells = config.cells
        self.ahead_m, self.behind_m = config.ahead_m, config.behind_m
        self.side_lanes = config.side_lanes
        self.lane_count = lane_count
        self.off_road_value = config.off_road_value
        self.near_edge = config.covered_by == "near_edge"
        cell_m = (config.ahead_m + config.behind_m) / config.cells
        # Each row's far and near edge, metres ahead of the agent's centre (row 0 farthest).
        self._top_m = config.ahead_m - cell_m * np.arange(config.cells)
        self._bottom_m = self._top_m - cell_m
        # Lane offsets of the columns, left to right (a lane to the left has a higher index).
        self._offsets = np.arange(config.side_lanes, -config.side_lanes - 1, -1)

    def space(self) -> SensorSpace:
        low = min(0, self.off_road_value)
        shape = (self.cells, self._offsets.size)
        return SensorSpace.uniform(shape, np.int8, low, 1)

    def facts(self) -> SensorFacts:
        """Rows from ``ahead_m`` ahead to ``behind_m`` behind; columns the lanes, left to
        right (``left_2, left_1, own, right_1, right_2`` with two side lanes)."""
        sides = range(self.side_lanes, 0, -1)
        columns = (*(f"left_{k}" for k in sides), "own", *(f"right_{k}" for k in sides[::-1]))
        return SensorFacts(columns=columns, ahead_m=self.ahead_m, behind_m=self.behind_m)

    def observe(self, scene: Scene) -> np.ndarray:
        st, n = scene.state, scene.agents
        half = scene.kinds.half_length[st.kind]  # (A, V)
        dx = st.x_m[:, None, :] - st.x_m[:, :n, None]  # (A, N, V): other - agent
        seen = np.broadcast_to(st.active[:, None, :], dx.shape).copy()
        seen[:, np.arange(n), np.arange(n)] = False  # not the agent itself
        front = (dx + half[:, None, :])[..., None]  # (A, N, V, 1)
        rear = (dx - half[:, None, :])[..., None]
        if self.near_edge:  # cells whose near edge is under the body: its length of them
            covers = (front >= self._bottom_m) & (rear < self._bottom_m)  # (A, N, V, cells)
        else:
            covers = (front > self._bottom_m) & (rear < self._top_m)
        covers &= seen[..., None]
        # (A, N, 1, columns): the lane of each column, for each agent.
        column_lane = (st.lane[:, :n, None] + self._offsets)[:, :, None, :]
        in_column = (st.lane[:, None, :, None] == column_lane) | (
            st.target_lane[:, None, :, None] == column_lane
        )  # (A, N, V, columns)
        # (A, N, cells, columns): some vehicle in that column covers that row.
        occupied = np.matmul(
            covers.swapaxes(-1, -2).astype(np.float32), in_column.astype(np.float32)
        )
        grid = (occupied > 0.0).astype(np.int8)
        off_road = (column_lane < 0) | (column_lane >= self.lane_count)  # (A, N, 1, columns)
        return np.where(off_road, np.int8(self.off_road_value), grid)
