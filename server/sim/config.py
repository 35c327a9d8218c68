"""Typed, frozen configuration of the simulation, with units in every name.

A preset is a complete :class:`SimConfig`. Every field can be overridden, either in Python with
:func:`dataclasses.replace` or, from the outside (command lines, the wire), with
:func:`apply_overrides`, which takes a flat mapping of dotted field names to plain values
(``{"road.lane_count": 7, "traffic.density": "heavy"}``) and checks each one against the
dataclass's type annotations. Values are validated in ``__post_init__``: a bad value is refused
with a :class:`ConfigError` that names the field, the value that came and what is allowed.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal, get_args, get_origin, get_type_hints


class ConfigError(ValueError):
    """A configuration value or name was refused; the message says what was expected."""


def _check(condition: bool, name: str, value: object, expected: str) -> None:
    if not condition:
        raise ConfigError(f"{name} = {value!r} is not allowed: expected {expected}")


def _check_range(name: str, value: float, low: float | None = None, high: float | None = None,
                 *, low_open: bool = False) -> None:
    ok = math.isfinite(value)
    if low is not None:
        ok = ok and (value > low if low_open else value >= low)
    if high is not None:
        ok = ok and value <= high
    lo = "" if low is None else (f"> {low}" if low_open else f">= {low}")
    hi = "" if high is None else f"<= {high}"
    _check(ok, name, value, "a finite number " + " and ".join(p for p in (lo, hi) if p))


def _check_interval(name: str, value: tuple[float, float], low: float = 0.0) -> None:
    _check(len(value) == 2 and all(math.isfinite(v) for v in value)
           and low <= value[0] <= value[1], name, value,
           f"a pair (min, max) with {low} <= min <= max")


Density = Literal["light", "medium", "heavy"]

# Ho (2018), Table 4: the most traffic cars simulated at once in each traffic condition.
DENSITY_VEHICLE_COUNT: dict[str, int] = {"light": 20, "medium": 40, "heavy": 60}


@dataclass(frozen=True, slots=True)
class RoadConfig:
    """A straight highway. Lanes are numbered from the right (0 = rightmost); +y points left."""

    lane_count: int = 5
    lane_width_m: float = 3.5
    # Guard rails stand this far outside the outer lane edges; the LIDAR sees them.
    barrier_offset_m: float = 1.0

    def __post_init__(self) -> None:
        _check(isinstance(self.lane_count, int) and 1 <= self.lane_count <= 12,
               "road.lane_count", self.lane_count, "an integer from 1 to 12")
        _check_range("road.lane_width_m", self.lane_width_m, 2.5, 6.0)
        _check_range("road.barrier_offset_m", self.barrier_offset_m, 0.0, 10.0)


@dataclass(frozen=True, slots=True)
class BehaviourConfig:
    """One traffic driver type (Ho 2018, Table 5): its share of the traffic, speed and manners."""

    share: float
    desired_speed_kmh: tuple[float, float]
    # MOBIL politeness p and switching threshold (m/s^2): low threshold = eager lane changer.
    politeness: float = 0.5
    lane_change_threshold_mps2: float = 0.3
    # Chance per second that a driver picks a new desired speed within its range
    # (Min et al.'s traffic randomly accelerates and brakes; 0 keeps a steady speed).
    speed_change_rate_per_s: float = 0.0

    def validate(self, name: str) -> None:
        _check_range(f"{name}.share", self.share, 0.0, 1.0)
        _check_interval(f"{name}.desired_speed_kmh", self.desired_speed_kmh, 1.0)
        _check_range(f"{name}.politeness", self.politeness, 0.0, 1.0)
        _check_range(f"{name}.lane_change_threshold_mps2", self.lane_change_threshold_mps2,
                     0.0, 10.0)
        _check_range(f"{name}.speed_change_rate_per_s", self.speed_change_rate_per_s, 0.0, 10.0)


# The order of the behaviours: their index is what the simulation stores per vehicle.
BEHAVIOURS: tuple[str, ...] = ("steady", "road_max", "lane_changer")


@dataclass(frozen=True, slots=True)
class TrafficConfig:
    """Traffic around the agents: IDM car-following, MOBIL lane changes, a treadmill of cars."""

    density: Density = "medium"
    # None takes the density's count (20 / 40 / 60); an integer overrides it.
    vehicle_count: int | None = None
    steady: BehaviourConfig = field(default_factory=lambda: BehaviourConfig(
        share=0.5, desired_speed_kmh=(45.0, 65.0), politeness=0.5,
        lane_change_threshold_mps2=1.0, speed_change_rate_per_s=0.05))
    road_max: BehaviourConfig = field(default_factory=lambda: BehaviourConfig(
        share=0.3, desired_speed_kmh=(68.0, 72.0), politeness=0.3,
        lane_change_threshold_mps2=0.5))
    lane_changer: BehaviourConfig = field(default_factory=lambda: BehaviourConfig(
        share=0.2, desired_speed_kmh=(68.0, 72.0), politeness=0.0,
        lane_change_threshold_mps2=0.1))
    # New traffic appears in these windows (metres ahead of / behind an agent) ...
    spawn_ahead_m: tuple[float, float] = (30.0, 90.0)
    spawn_behind_m: tuple[float, float] = (30.0, 60.0)
    # ... and is recycled once it is further than this from every agent.
    keep_ahead_m: float = 200.0
    keep_behind_m: float = 150.0
    vehicle_length_m: float = 4.5
    vehicle_width_m: float = 1.8
    # IDM (Treiber et al.): time headway, standstill gap, acceleration, comfortable braking.
    time_headway_s: float = 1.5
    min_gap_m: float = 2.0
    max_accel_mps2: float = 1.5
    comfort_decel_mps2: float = 2.5
    max_decel_mps2: float = 9.0
    # MOBIL's safety criterion: a lane change may not make the new follower brake harder.
    safe_decel_mps2: float = 4.0
    lane_change_duration_s: float = 2.5

    def __post_init__(self) -> None:
        _check(self.density in DENSITY_VEHICLE_COUNT, "traffic.density", self.density,
               f"one of {sorted(DENSITY_VEHICLE_COUNT)}")
        _check(self.vehicle_count is None
               or (isinstance(self.vehicle_count, int) and 0 <= self.vehicle_count <= 200),
               "traffic.vehicle_count", self.vehicle_count, "None or an integer from 0 to 200")
        for name in BEHAVIOURS:
            getattr(self, name).validate(f"traffic.{name}")
        total = sum(getattr(self, name).share for name in BEHAVIOURS)
        _check(total > 0, "traffic.{steady,road_max,lane_changer}.share", total,
               "shares that add up to more than 0")
        _check_interval("traffic.spawn_ahead_m", self.spawn_ahead_m)
        _check_interval("traffic.spawn_behind_m", self.spawn_behind_m)
        _check_range("traffic.keep_ahead_m", self.keep_ahead_m, self.spawn_ahead_m[1], 5000.0)
        _check_range("traffic.keep_behind_m", self.keep_behind_m, self.spawn_behind_m[1], 5000.0)
        _check_range("traffic.vehicle_length_m", self.vehicle_length_m, 2.0, 20.0)
        _check_range("traffic.vehicle_width_m", self.vehicle_width_m, 1.0, 3.0)
        _check_range("traffic.time_headway_s", self.time_headway_s, 0.1, 5.0)
        _check_range("traffic.min_gap_m", self.min_gap_m, 0.5, 20.0)
        _check_range("traffic.max_accel_mps2", self.max_accel_mps2, 0.1, 10.0)
        _check_range("traffic.comfort_decel_mps2", self.comfort_decel_mps2, 0.1, 10.0)
        _check_range("traffic.max_decel_mps2", self.max_decel_mps2, self.comfort_decel_mps2, 15.0)
        _check_range("traffic.safe_decel_mps2", self.safe_decel_mps2, 0.1, self.max_decel_mps2)
        _check_range("traffic.lane_change_duration_s", self.lane_change_duration_s, 0.5, 10.0)

    @property
    def resolved_vehicle_count(self) -> int:
        """The most traffic cars on the road at once."""
        if self.vehicle_count is not None:
            return self.vehicle_count
        return DENSITY_VEHICLE_COUNT[self.density]

    @property
    def behaviours(self) -> tuple[BehaviourConfig, ...]:
        return tuple(getattr(self, name) for name in BEHAVIOURS)


@dataclass(frozen=True, slots=True)
class EgoConfig:
    """The controlled car: DAS functions (adaptive cruise, lane keeping, AEB) under the actions."""

    cruise_min_kmh: float = 40.0
    cruise_max_kmh: float = 80.0
    cruise_step_kmh: float = 5.0
    initial_speed_kmh: float = 60.0
    length_m: float = 4.5
    width_m: float = 1.8
    # Adaptive cruise control is an IDM with these parameters and the cruise target as v0.
    time_headway_s: float = 1.2
    min_gap_m: float = 2.0
    max_accel_mps2: float = 2.0
    comfort_decel_mps2: float = 3.0
    # Autonomous emergency braking: full braking when the time to collision falls below this.
    aeb_time_to_collision_s: float = 1.5
    aeb_decel_mps2: float = 8.0
    # Ho's emergency brake: braking at least this hard (m/s^2) ...
    emergency_decel_mps2: float = 4.0
    # ... with at least this speed difference to the car ahead (Ho 2018, section 6.2).
    emergency_speed_diff_kmh: float = 20.0
    lane_change_duration_s: float = 2.0
    # Driver assistance refuses to start a lane change into a lane that is not clear from
    # lane_change_clear_behind_m behind to lane_change_clear_ahead_m ahead, bumper to bumper,
    # counting cars already moving into it (the action mask says so): Min et al.'s cars change
    # lanes only without a side warning. Each window grows by the closing speed of a car there
    # times lane_change_closing_time_s: a car 10 m/s faster behind needs 10 m more. False lets
    # every change start, whoever is beside.
    lane_change_check: bool = True
    lane_change_clear_ahead_m: float = 2.0
    lane_change_clear_behind_m: float = 4.0
    lane_change_closing_time_s: float = 1.0

    def __post_init__(self) -> None:
        _check_range("ego.cruise_min_kmh", self.cruise_min_kmh, 0.0, 300.0)
        _check_range("ego.cruise_max_kmh", self.cruise_max_kmh, self.cruise_min_kmh, 300.0)
        _check_range("ego.cruise_step_kmh", self.cruise_step_kmh, 0.0, 50.0, low_open=True)
        _check_range("ego.initial_speed_kmh", self.initial_speed_kmh,
                     self.cruise_min_kmh, self.cruise_max_kmh)
        _check_range("ego.length_m", self.length_m, 2.0, 20.0)
        _check_range("ego.width_m", self.width_m, 1.0, 3.0)
        _check_range("ego.time_headway_s", self.time_headway_s, 0.1, 5.0)
        _check_range("ego.min_gap_m", self.min_gap_m, 0.5, 20.0)
        _check_range("ego.max_accel_mps2", self.max_accel_mps2, 0.1, 10.0)
        _check_range("ego.comfort_decel_mps2", self.comfort_decel_mps2, 0.1, 10.0)
        _check_range("ego.aeb_time_to_collision_s", self.aeb_time_to_collision_s, 0.0, 10.0)
        _check_range("ego.aeb_decel_mps2", self.aeb_decel_mps2, 0.1, 15.0)
        _check_range("ego.emergency_decel_mps2", self.emergency_decel_mps2, 0.1, 15.0)
        _check_range("ego.emergency_speed_diff_kmh", self.emergency_speed_diff_kmh, 0.0, 300.0)
        _check_range("ego.lane_change_duration_s", self.lane_change_duration_s, 0.5, 10.0)
        _check_range("ego.lane_change_clear_ahead_m", self.lane_change_clear_ahead_m, 0.0, 100.0)
        _check_range("ego.lane_change_clear_behind_m", self.lane_change_clear_behind_m, 0.0,
                     100.0)
        _check_range("ego.lane_change_closing_time_s", self.lane_change_closing_time_s, 0.0,
                     10.0)


@dataclass(frozen=True, slots=True)
class LidarConfig:
    """A 360-degree LIDAR at the car's centre.

    Ray i points i * (360 / ray_count) degrees counter-clockwise (to the left, seen from above)
    from straight ahead: with 360 rays, index 0 is straight ahead, 90 is left, 180 is behind and
    270 is right. Values are metres, clipped at ``max_range_m``.
    """

    enabled: bool = True
    ray_count: int = 360
    max_range_m: float = 80.0

    def __post_init__(self) -> None:
        _check(isinstance(self.enabled, bool), "lidar.enabled", self.enabled, "true or false")
        _check(isinstance(self.ray_count, int) and 4 <= self.ray_count <= 3600,
               "lidar.ray_count", self.ray_count, "an integer from 4 to 3600")
        _check_range("lidar.max_range_m", self.max_range_m, 1.0, 1000.0)


@dataclass(frozen=True, slots=True)
class CameraConfig:
    """A front camera at the driver's seat, rendered in software (a pinhole perspective view)."""

    enabled: bool = True
    width_px: int = 84
    height_px: int = 84
    horizontal_fov_deg: float = 70.0
    rgb: bool = False
    mount_height_m: float = 1.2
    # Pitched down so that more of the image shows road than sky.
    pitch_down_deg: float = 6.0
    mount_forward_m: float = 0.3
    max_distance_m: float = 200.0

    def __post_init__(self) -> None:
        _check(isinstance(self.enabled, bool), "camera.enabled", self.enabled, "true or false")
        _check(isinstance(self.rgb, bool), "camera.rgb", self.rgb, "true or false")
        for name in ("width_px", "height_px"):
            value = getattr(self, name)
            _check(isinstance(value, int) and 8 <= value <= 1024, f"camera.{name}", value,
                   "an integer from 8 to 1024")
        _check_range("camera.horizontal_fov_deg", self.horizontal_fov_deg, 10.0, 160.0)
        _check_range("camera.mount_height_m", self.mount_height_m, 0.3, 5.0)
        _check_range("camera.pitch_down_deg", self.pitch_down_deg, -30.0, 45.0)
        _check_range("camera.mount_forward_m", self.mount_forward_m, -5.0, 5.0)
        _check_range("camera.max_distance_m", self.max_distance_m, 10.0, 2000.0)


@dataclass(frozen=True, slots=True)
class RewardConfig:
    """Min et al. (2018) Table I by default; every term is reported on its own in info."""

    speed_min_kmh: float = 40.0
    speed_max_kmh: float = 80.0
    speed_reward_max: float = 1.0
    # Min et al.'s code keeps the speed term in [0, r_v,max]; False leaves Eq. (1) unclipped.
    clip_speed_term: bool = True
    collision: float = -10.0
    lane_change: float = -0.25
    overtake: float = 0.5
    # Reward per car that passes the agent (Ho: -1; Min et al.: none).
    passed: float = 0.0
    # When a car the agent overtook passes it back, take that overtake back (count and reward).
    undo_overtake_when_passed_back: bool = False

    def __post_init__(self) -> None:
        _check_range("reward.speed_min_kmh", self.speed_min_kmh, 0.0, 300.0)
        _check_range("reward.speed_max_kmh", self.speed_max_kmh, self.speed_min_kmh, 300.0,
                     low_open=True)
        for name in ("speed_reward_max", "collision", "lane_change", "overtake", "passed"):
            _check_range(f"reward.{name}", getattr(self, name), -1000.0, 1000.0)
        for name in ("clip_speed_term", "undo_overtake_when_passed_back"):
            _check(isinstance(getattr(self, name), bool), f"reward.{name}",
                   getattr(self, name), "true or false")


@dataclass(frozen=True, slots=True)
class EpisodeConfig:
    """Time: one decision spans ``frames_per_decision`` physics frames of ``physics_dt_s``."""

    max_decisions: int = 1000
    frames_per_decision: int = 4
    physics_dt_s: float = 0.1

    def __post_init__(self) -> None:
        _check(isinstance(self.max_decisions, int) and self.max_decisions >= 1,
               "episode.max_decisions", self.max_decisions, "an integer >= 1")
        _check(isinstance(self.frames_per_decision, int) and 1 <= self.frames_per_decision <= 100,
               "episode.frames_per_decision", self.frames_per_decision, "an integer from 1 to 100")
        _check_range("episode.physics_dt_s", self.physics_dt_s, 0.0, 0.1, low_open=True)

    @property
    def decision_period_s(self) -> float:
        """Simulated seconds per decision."""
        return self.frames_per_decision * self.physics_dt_s


@dataclass(frozen=True, slots=True)
class SimConfig:
    """A complete scenario: what a preset names and what an arena runs."""

    preset: str = "min2018"
    road: RoadConfig = field(default_factory=RoadConfig)
    traffic: TrafficConfig = field(default_factory=TrafficConfig)
    ego: EgoConfig = field(default_factory=EgoConfig)
    lidar: LidarConfig = field(default_factory=LidarConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)
    episode: EpisodeConfig = field(default_factory=EpisodeConfig)

    def __post_init__(self) -> None:
        _check(self.lidar.enabled or self.camera.enabled, "lidar.enabled / camera.enabled",
               (self.lidar.enabled, self.camera.enabled), "at least one sensor enabled")


# --- overrides -------------------------------------------------------------------------------

PlainValue = bool | int | float | str | None | list | tuple
# The preset's name says where the overrides started from; it is not itself a setting.
NOT_OVERRIDABLE = frozenset({"preset"})


def field_names(config: object, prefix: str = "") -> list[str]:
    """Every overridable dotted field name of a config dataclass, leaves only."""
    names: list[str] = []
    for f in dataclasses.fields(config):  # type: ignore[arg-type]
        if f"{prefix}{f.name}" in NOT_OVERRIDABLE:
            continue
        value = getattr(config, f.name)
        if dataclasses.is_dataclass(value):
            names.extend(field_names(value, f"{prefix}{f.name}."))
        else:
            names.append(f"{prefix}{f.name}")
    return names


def _coerce(name: str, annotation: Any, value: object) -> object:
    """Convert a plain value (from JSON, msgpack or a command line) to the annotated type."""
    origin = get_origin(annotation)
    if origin is Literal:
        allowed = get_args(annotation)
        _check(value in allowed, name, value, f"one of {list(allowed)}")
        return value
    if origin in (typing.Union, types.UnionType):
        options = get_args(annotation)
        if value is None:
            _check(type(None) in options, name, value, f"a value of type {annotation}")
            return None
        for option in options:
            if option is not type(None):
                return _coerce(name, option, value)
    if origin is tuple:
        item_types = get_args(annotation)
        _check(isinstance(value, (list, tuple)) and len(value) == len(item_types), name, value,
               f"a list of {len(item_types)} values")
        return tuple(_coerce(name, t, v) for t, v in zip(item_types, value))  # type: ignore[arg-type]
    if annotation is bool:
        _check(isinstance(value, bool), name, value, "true or false")
        return value
    if annotation is int:
        _check(isinstance(value, int) and not isinstance(value, bool), name, value, "an integer")
        return value
    if annotation is float:
        _check(isinstance(value, (int, float)) and not isinstance(value, bool), name, value,
               "a number")
        return float(value)  # type: ignore[arg-type]
    if annotation is str:
        _check(isinstance(value, str), name, value, "a string")
        return value
    raise ConfigError(f"{name} cannot be overridden with a plain value")


def apply_overrides(config: SimConfig, overrides: Mapping[str, PlainValue]) -> SimConfig:
    """A copy of ``config`` with dotted fields replaced, every value checked against its type."""
    for dotted, value in overrides.items():
        if dotted in NOT_OVERRIDABLE:
            raise ConfigError(f"{dotted!r} names the preset an override starts from: choose it "
                              "by name, it cannot be overridden")
        config = _replace_path(config, dotted.split("."), dotted, value)
    return config


def _replace_path(node: Any, path: list[str], dotted: str, value: object) -> Any:
    hints = get_type_hints(type(node))
    names = [f.name for f in dataclasses.fields(node)]
    head = path[0]
    if head not in names:
        parent = dotted[: len(dotted) - len(".".join(path))]
        allowed = field_names(node, parent)
        raise ConfigError(f"unknown configuration field {dotted!r}: at this level the fields are "
                          f"{', '.join(allowed)}")
    current = getattr(node, head)
    if len(path) == 1:
        if dataclasses.is_dataclass(current):
            raise ConfigError(f"{dotted!r} is a group of fields, not a value: set one of "
                              f"{', '.join(dotted + '.' + n for n in field_names(current))}")
        new_value = _coerce(dotted, hints[head], value)
    else:
        if not dataclasses.is_dataclass(current):
            raise ConfigError(f"unknown configuration field {dotted!r}: {'.'.join(path[:1])} "
                              "has no sub-fields")
        new_value = _replace_path(current, path[1:], dotted, value)
    return dataclasses.replace(node, **{head: new_value})
