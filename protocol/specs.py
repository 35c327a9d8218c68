"""The behaviour spec a server sends with every Opened: what an agent sees (each observation's
box, named columns and reach) and drives (the actions, the road, the car), ML-Agents'
BehaviorSpec with the facts a consumer needs to read the observations."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .errors import DecodeError
from .records import (
    MAX_AGENTS_PER_ARENA,
    MAX_ARRAY_DIMS,
    WIRE_DTYPES,
    Part,
    check_array,
    check_name,
    check_range,
)
from .vocabulary import ACTION_COUNT


@dataclass(frozen=True, eq=False)
class Reach(Part):
    """How far an observation sees, in metres from the car's centre along the road (ahead,
    behind), across it (to either side) and along its rays (range); 0 where it does not
    apply."""

    ahead_m: float = 0.0  # how far ahead of the car's centre along the road (a grid, a map)
    behind_m: float = 0.0  # how far behind the car's centre along the road
    side_m: float = 0.0  # how far to either side, across the road
    range_m: float = 0.0  # how far along its rays (the LIDAR's range)

    def check(self) -> None:
        for name in ("ahead_m", "behind_m", "side_m", "range_m"):
            value = getattr(self, name)
            if not 0.0 <= value < 1e6:
                raise DecodeError(f"reach {name} must be from 0 to 1e6 m, got {value}")


@dataclass(frozen=True, eq=False)
class RoadSpec(Part):
    """The road the agents drive: its lanes."""

    lane_count: int  # lanes, numbered from the right
    lane_width_m: float  # each lane's width

    def check(self) -> None:
        check_range("lane count", self.lane_count, 1, 64)
        if not 0.0 < self.lane_width_m < 100.0:
            raise DecodeError(f"lane width must be from 0 to 100 m, got {self.lane_width_m}")


@dataclass(frozen=True, eq=False)
class CarSpec(Part):
    """An agent's car: its body and the speeds its actions move between."""

    length_m: float  # bumper to bumper
    width_m: float  # side to side
    min_speed_kmh: float  # the lowest speed the speed actions set
    max_speed_kmh: float  # the highest

    def check(self) -> None:
        if not (0.0 < self.length_m < 100.0 and 0.0 < self.width_m < 100.0):
            raise DecodeError(
                f"car length and width must be from 0 to 100 m, got {self.length_m} and "
                f"{self.width_m}"
            )
        if not 0.0 <= self.min_speed_kmh <= self.max_speed_kmh < 1e4:
            raise DecodeError(
                f"car speeds must be 0 <= min <= max, got {self.min_speed_kmh} and "
                f"{self.max_speed_kmh} km/h"
            )


@dataclass(frozen=True, eq=False)
class ColumnScale(Part):
    """A normalised column: the quantity it shows ran from ``low`` to ``high`` and is mapped to
    [-1, 1] (``2 (v - low) / (high - low) - 1``, clipped there where the column's bounds say
    so), so that a consumer reads the quantity back as ``low + (value + 1) / 2 (high - low)``
    (highway-env's Kinematics features: x, y in m, vx, vy in m/s)."""

    column: str  # the column's name, one of its observation's columns
    low: float  # the quantity shown as -1
    high: float  # the quantity shown as 1

    def check(self) -> None:
        if not (math.isfinite(self.low) and math.isfinite(self.high) and self.low < self.high):
            raise DecodeError(
                f"column {self.column!r} scale must be finite with low < high, got "
                f"{self.low} and {self.high}"
            )


@dataclass(frozen=True, eq=False)
class ObservationSpec(Part):
    """One observation of one agent: a Box of ``shape`` and ``dtype`` within [low, high], the
    names of its last axis' entries where they are named (``columns``: the ego vector's fields)
    and how far it sees (``reach``; None for what sees nothing of the road, as the action
    stack)."""

    name: str  # the observation's key (lidar, camera, ego, grid, ...)
    shape: tuple[int, ...]  # one agent's shape
    dtype: str  # a wire dtype
    low: np.ndarray  # lower bounds, of shape and dtype
    high: np.ndarray  # upper bounds, of shape and dtype
    # names of the last axis' entries, where named
    columns: tuple[str, ...] = field(default=(), metadata={"since": 5})
    # how far it sees; None: nothing of the road
    reach: Reach | None = field(default=None, metadata={"since": 5})
    # the normalised columns and the range each maps to [-1, 1]; none: no column is normalised
    scales: tuple[ColumnScale, ...] = field(default=(), metadata={"since": 11})

    def check(self) -> None:
        check_name("observation name", self.name)
        if self.dtype not in WIRE_DTYPES:
            raise DecodeError(
                f"observation {self.name!r} dtype must be one of "
                f"{sorted(WIRE_DTYPES)}, got {self.dtype!r}"
            )
        if not 1 <= len(self.shape) <= MAX_ARRAY_DIMS - 1 or min(self.shape) < 1:
            raise DecodeError(
                f"observation {self.name!r} shape must have 1 to "
                f"{MAX_ARRAY_DIMS - 1} positive sizes, got {self.shape}"
            )
        for bound in ("low", "high"):
            check_array(
                f"observation {self.name!r} {bound}", getattr(self, bound), self.dtype, self.shape
            )
        if self.columns and len(self.columns) != self.shape[-1]:
            raise DecodeError(
                f"observation {self.name!r} names {len(self.columns)} columns for a last axis "
                f"of {self.shape[-1]}"
            )
        scaled = [scale.column for scale in self.scales]
        unknown = [name for name in scaled if name not in self.columns]
        if unknown or len(set(scaled)) != len(scaled):
            raise DecodeError(
                f"observation {self.name!r} scales distinct columns of its own "
                f"{list(self.columns)}, got {scaled}"
            )

    def scale(self, column: str) -> ColumnScale | None:
        """How ``column`` is normalised; None where it shows its quantity as it is."""
        for scale in self.scales:
            if scale.column == column:
                return scale
        return None


@dataclass(frozen=True, eq=False)
class BehaviourSpec(Part):
    """Everything a client needs to rebuild the in-process spaces (ML-Agents' BehaviorSpec)."""

    name: str  # the behaviour's name (ML-Agents' behavior name)
    preset: str  # the preset the arenas run
    observations: tuple[ObservationSpec, ...]  # what each agent observes, in order
    action_branches: tuple[int, ...]  # one discrete branch of ACTION_COUNT actions
    action_names: tuple[str, ...]  # the actions, in index order
    reward_terms: tuple[str, ...]  # the reward's terms, in the order they are summed and reported
    metric_fields: tuple[str, ...]  # the columns of Steps.metrics
    decision_period_s: float  # simulated seconds per decision
    max_episode_steps: int  # decisions before an episode is truncated
    agents_per_arena: int  # car slots per arena
    config_json: str
    """the server's resolved configuration, a record (run records, checkpoints): what a
    consumer reads of it is in the typed fields"""
    # lanes (None from a 1.4 server)
    road: RoadSpec | None = field(default=None, metadata={"since": 5})
    # the agent's car (None from a 1.4 server)
    car: CarSpec | None = field(default=None, metadata={"since": 5})

    def check(self) -> None:
        names = [o.name for o in self.observations]
        if not names or len(set(names)) != len(names):
            raise DecodeError(f"observation names must be distinct and at least one, got {names}")
        if self.action_branches != (ACTION_COUNT,):
            raise DecodeError(
                f"action branches must be ({ACTION_COUNT},), got {self.action_branches}"
            )
        if len(self.action_names) != ACTION_COUNT:
            raise DecodeError(f"expected {ACTION_COUNT} action names, got {self.action_names}")
        check_range("agents per arena", self.agents_per_arena, 1, MAX_AGENTS_PER_ARENA)
        check_range("max episode steps", self.max_episode_steps, 1, 2**62)
        if not self.decision_period_s > 0:
            raise DecodeError(f"decision period must be > 0 s, got {self.decision_period_s}")

    def observation(self, name: str) -> ObservationSpec:
        for spec in self.observations:
            if spec.name == name:
                return spec
        raise KeyError(name)

    def has(self, name: str) -> bool:
        """Whether the agents observe ``name``."""
        return any(spec.name == name for spec in self.observations)
