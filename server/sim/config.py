"""A complete scenario as typed, frozen configuration, and overrides by dotted name.

:class:`SimConfig` composes the sections each part of the simulation owns, and a preset
(:mod:`.presets`) is one complete SimConfig: the road (:mod:`.road`), the traffic
(:mod:`.traffic.config`), the controlled car and its driver assistance (:mod:`.assist`), the
sensors (:mod:`.sensors`), the reward (:mod:`.rewards`) and the episode (:mod:`.episodes`).
Every value has its unit in its name and is checked where it is defined: a bad one is refused
with a :class:`ConfigError` that names the field, the value that came and what is allowed.

Every field can be overridden, in Python with :func:`dataclasses.replace` or, from the outside
(command lines, the wire), with :func:`apply_overrides`, which takes a flat mapping of dotted
field names to plain values (``{"road.lane_count": 7, "traffic.density": "heavy"}``) and
checks each one against the dataclasses' type annotations.
"""

from __future__ import annotations

import dataclasses
import difflib
import json
import re
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, Literal, get_args, get_origin, get_type_hints

from overtake.protocol.vocabulary import DEFAULT_PRESET

from .assist import EgoConfig
from .episodes import EpisodeConfig
from .highway_scene.config import HighwaySceneConfig
from .rewards import RewardConfig
from .road import RoadConfig
from .sensors.action_history import ActionHistoryConfig
from .sensors.base import SensorConfig
from .sensors.camera import CameraConfig
from .sensors.ego import EgoVectorConfig
from .sensors.grid import OccupancyGridConfig
from .sensors.kinematics import KinematicsConfig
from .sensors.lidar import LidarConfig
from .sensors.lidar_map import LidarMapConfig
from .traffic.config import TrafficConfig
from .validation import ConfigError, check

__all__ = [
    "ConfigError",
    "PlainValue",
    "SimConfig",
    "Translated",
    "apply_overrides",
    "as_json",
    "field_names",
]


@dataclass(frozen=True, slots=True)
class SimConfig:
    """A complete scenario: what a preset names and what an arena runs.

    The sensor sections (each a :class:`~.sensors.base.SensorConfig`) are the simulation's
    sensors; the observation holds the enabled ones in this order.
    """

    preset: str = DEFAULT_PRESET
    road: RoadConfig = field(default_factory=RoadConfig)
    traffic: TrafficConfig = field(default_factory=TrafficConfig)
    ego: EgoConfig = field(default_factory=EgoConfig)
    lidar: LidarConfig = field(default_factory=LidarConfig)
    camera: CameraConfig = field(default_factory=CameraConfig)
    ego_vector: EgoVectorConfig = field(default_factory=EgoVectorConfig)
    grid: OccupancyGridConfig = field(default_factory=OccupancyGridConfig)
    action_history: ActionHistoryConfig = field(default_factory=ActionHistoryConfig)
    lidar_map: LidarMapConfig = field(default_factory=LidarMapConfig)
    kinematics: KinematicsConfig = field(default_factory=KinematicsConfig)
    highway_scene: HighwaySceneConfig = field(default_factory=HighwaySceneConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)
    episode: EpisodeConfig = field(default_factory=EpisodeConfig)

    def __post_init__(self) -> None:
        sensors = self.sensor_sections()
        check(
            any(section.enabled for section in sensors.values()),
            " / ".join(f"{name}.enabled" for name in sensors),
            tuple(section.enabled for section in sensors.values()),
            "at least one sensor enabled",
        )

    def sensor_sections(self) -> dict[str, SensorConfig]:
        """The sensor sections, by field name, in order."""
        return {
            f.name: value
            for f in dataclasses.fields(self)
            if isinstance(value := getattr(self, f.name), SensorConfig)
        }

    def observing(self, observations: tuple[str, ...]) -> SimConfig:
        """This configuration with only the sensors of ``observations`` on, the others off (a
        trainer's request, protocol 1.10: a sensor nobody reads costs its rendering; the
        camera is a third of a step); none named: as it is. A name whose sensor is not on is a
        :class:`ConfigError` naming those that are."""
        if not observations:
            return self
        sections = self.sensor_sections()
        on = {s.OBSERVATION: name for name, s in sections.items() if s.enabled}
        missing = [o for o in observations if o not in on]
        if missing:
            raise ConfigError(
                f"observations {missing} are not observed by preset {self.preset} with these "
                f"settings (it observes {', '.join(on)}; a sensor is switched on with "
                "<sensor>.enabled=true)"
            )
        off = {
            name: dataclasses.replace(sections[name], enabled=False)  # type: ignore[type-var]
            for observation, name in on.items()
            if observation not in observations
        }
        return dataclasses.replace(self, **off)  # type: ignore[arg-type]

    def reading_ego_fields(self, ego_fields: tuple[str, ...]) -> SimConfig:
        """This configuration with the ego vector holding ``ego_fields``, in that order (a
        trainer's request, protocol 1.11: the camera-only network of Min et al.'s ablation
        reads the car's speed alone); none named: as it is. A :class:`ConfigError` where the
        ego vector is off or a name is not one of its fields."""
        if not ego_fields:
            return self
        if not self.ego_vector.enabled:
            raise ConfigError(
                f"ego fields {list(ego_fields)} were asked for, and preset {self.preset} with "
                "these settings observes no ego vector (ego_vector.enabled is false)"
            )
        return dataclasses.replace(
            self, ego_vector=dataclasses.replace(self.ego_vector, fields=tuple(ego_fields))
        )


# --- overrides -------------------------------------------------------------------------------

PlainValue = bool | int | float | str | None | list | tuple


@dataclass(frozen=True)
class Translated:
    """A configuration written in another simulator's words (highway-env's ``config`` dict),
    translated into this simulator's settings (:mod:`.translations`): the overrides it
    stands for, and for each the words the user gave it in, so that a refused value is said
    as the user wrote it."""

    overrides: Mapping[str, PlainValue]
    given_as: Mapping[str, str] = field(default_factory=dict)

    def in_users_words(self, message: str) -> str:
        """A refusal naming this simulator's setting, said with the key the user gave (the
        setting after it, in brackets)."""
        for setting in sorted(self.given_as, key=len, reverse=True):
            if message.startswith(setting + " "):
                return f"{self.given_as[setting]}{message[len(setting) :]} (overtake's {setting})"
            message = re.sub(
                rf"(?<![\w.]){re.escape(setting)}(?![\w.])",
                f"{self.given_as[setting]} ({setting})",
                message,
            )
        return message


# The preset's name says where the overrides started from; it is not itself a setting.
NOT_OVERRIDABLE = frozenset({"preset"})


def as_json(config: SimConfig) -> dict[str, Any]:
    """A configuration as JSON holds it (lists for tuples): an environment's ``sim_config``,
    and so what an episode record keeps."""
    result: dict[str, Any] = json.loads(json.dumps(dataclasses.asdict(config)))
    return result


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
        check(value in allowed, name, value, f"one of {list(allowed)}")
        return value
    if origin in (typing.Union, types.UnionType):
        options = get_args(annotation)
        if value is None:
            check(type(None) in options, name, value, f"a value of type {annotation}")
            return None
        for option in options:
            if option is not type(None):
                return _coerce(name, option, value)
    if origin is tuple:
        item_types = get_args(annotation)
        variadic = item_types[1:] == (Ellipsis,)
        wanted = "a list of values" if variadic else f"a list of {len(item_types)} values"
        if not isinstance(value, (list, tuple)) or not (variadic or len(value) == len(item_types)):
            raise ConfigError(f"{name} = {value!r} is not allowed: expected {wanted}")
        if variadic:
            return tuple(_coerce(name, item_types[0], v) for v in value)
        return tuple(_coerce(name, t, v) for t, v in zip(item_types, value, strict=True))
    if annotation is bool:
        check(isinstance(value, bool), name, value, "true or false")
        return value
    if annotation is int:
        check(isinstance(value, int) and not isinstance(value, bool), name, value, "an integer")
        return value
    if annotation is float:
        check(
            isinstance(value, (int, float)) and not isinstance(value, bool), name, value, "a number"
        )
        return float(value)  # type: ignore[arg-type]
    if annotation is str:
        check(isinstance(value, str), name, value, "a string")
        return value
    raise ConfigError(f"{name} cannot be overridden with a plain value")


def apply_overrides(config: SimConfig, overrides: Mapping[str, PlainValue]) -> SimConfig:
    """A copy of ``config`` with dotted fields replaced, every value checked against its type."""
    for dotted, value in overrides.items():
        if dotted in NOT_OVERRIDABLE:
            raise ConfigError(
                f"{dotted!r} names the preset an override starts from: choose it "
                "by name, it cannot be overridden"
            )
        config = _replace_path(config, dotted.split("."), dotted, value)
    return config


# How many of a level's field names an unknown field's error lists.
SHOWN_FIELDS = 8


def _nearest(name: str, names: list[str]) -> list[str]:
    """The names a typo of ``name`` most likely meant: the closest (difflib's ratio at least
    0.75), and any as close as it within 0.03 (the shared "traffic." of every candidate would
    otherwise make many look near)."""
    scored = sorted(
        ((difflib.SequenceMatcher(None, name, other).ratio(), other) for other in names),
        reverse=True,
    )
    if not scored or scored[0][0] < 0.75:
        return []
    best = scored[0][0]
    return [other for ratio, other in scored[:3] if ratio >= best - 0.03]


def _replace_path(node: Any, path: list[str], dotted: str, value: object) -> Any:
    hints = get_type_hints(type(node))
    names = [f.name for f in dataclasses.fields(node)]
    head = path[0]
    if head not in names:
        parent = dotted[: len(dotted) - len(".".join(path))]
        allowed = field_names(node, parent)
        # The nearest names first (a typo), then a few of the others: the whole list of some
        # levels is a screenful (docs/presets.md has every field).
        near = _nearest(dotted, allowed)
        hint = f"did you mean {' or '.join(near)}? " if near else ""
        shown = ", ".join(allowed[:SHOWN_FIELDS])
        more = f", ... ({len(allowed) - SHOWN_FIELDS} more)" if len(allowed) > SHOWN_FIELDS else ""
        raise ConfigError(
            f"unknown configuration field {dotted!r}: {hint}the fields at this level are "
            f"{shown}{more}"
        )
    current = getattr(node, head)
    if len(path) == 1:
        if dataclasses.is_dataclass(current):
            raise ConfigError(
                f"{dotted!r} is a group of fields, not a value: set one of "
                f"{', '.join(dotted + '.' + n for n in field_names(current))}"
            )
        new_value = _coerce(dotted, hints[head], value)
    else:
        if not dataclasses.is_dataclass(current):
            raise ConfigError(
                f"unknown configuration field {dotted!r}: {'.'.join(path[:1])} has no sub-fields"
            )
        new_value = _replace_path(current, path[1:], dotted, value)
    return dataclasses.replace(node, **{head: new_value})
