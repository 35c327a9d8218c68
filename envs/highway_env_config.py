"""highway-env's ``config`` dict read for the presets ``highway-fast`` and ``highway``
(:mod:`overtake.envs.highway_env_like`): each key highway-env's scenes take is turned into
overtake's settings, framing of the picture or action set, or said (once, in one line) as having
no effect here; any other key is refused by name with the nearest known one suggested, and a
refused value is said with the key the user gave. Every refusal is a
:class:`~overtake.protocol.errors.BadConfig` (a ``ValueError``).
"""

from __future__ import annotations

import difflib
import math
import re
import sys
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from overtake.protocol.errors import BadConfig

from .faces import PictureView

# highway-env's DiscreteMetaAction numbers -> overtake's (keep 0, cruise up 1, cruise down 2,
# lane left 3, lane right 4), and back: its whole set, the default.
TO_OVERTAKE = np.array([3, 0, 4, 1, 2], dtype=np.int64)
FROM_OVERTAKE = np.argsort(TO_OVERTAKE)
ACTION_LABELS = ("LANE_LEFT", "IDLE", "LANE_RIGHT", "FASTER", "SLOWER")
# Each of highway-env's labels as overtake's action, and its sets without lateral or without
# longitudinal actions (DiscreteMetaAction's ACTIONS_LONGI and ACTIONS_LAT, in its numbers).
OVERTAKE_ACTION = {"LANE_LEFT": 3, "IDLE": 0, "LANE_RIGHT": 4, "FASTER": 1, "SLOWER": 2}
LONGITUDINAL_LABELS = ("SLOWER", "IDLE", "FASTER")
LATERAL_LABELS = ("LANE_LEFT", "IDLE", "LANE_RIGHT")

# Each preset's physics frames a second and episode length in seconds, at a decision a second
# (server/sim/highway_scene/presets.py, from highway-env's configurations).
PRESET_TIMES = {"highway-fast": (5, 30), "highway": (15, 40)}

# highway-env's keys these ids take, each with overtake's setting (or how it maps).
_SCENE = "highway_scene."
_DIRECT: dict[str, str] = {
    "lanes_count": "road.lane_count",
    "vehicles_count": "traffic.vehicle_count",
    "vehicles_density": _SCENE + "vehicles_density",
    "ego_spacing": _SCENE + "ego_spacing",
    "collision_reward": _SCENE + "collision_reward",
    "right_lane_reward": _SCENE + "right_lane_reward",
    "high_speed_reward": _SCENE + "high_speed_reward",
    "lane_change_reward": _SCENE + "lane_change_reward",
    "reward_speed_range": _SCENE + "reward_speed_range_mps",
    "normalize_reward": _SCENE + "normalize_reward",
    "offroad_terminal": _SCENE + "offroad_terminal",
}
# highway-env's viewer settings that frame render()'s picture (PictureView).
VIEW_KEYS: dict[str, str] = {
    "screen_width": "the picture's width (pixels)",
    "screen_height": "the picture's height (pixels)",
    "scaling": "the picture's pixels a metre",
    "centering_position": "where the car sits in the picture",
}
# Keys taken that change nothing here, with highway-env's defaults: a value other than the
# default is said once, in one line (a warning), as having no effect.
NO_EFFECT_KEYS: dict[str, Any] = {
    "show_trajectories": False,
    "render_agent": True,
    "offscreen_rendering": None,
    "manual_control": False,
    "real_time_rendering": False,
    "neighbour_vehicles_connected_lanes": False,
}
NO_EFFECT_WHY = (
    "overtake draws its own top-down picture (render_mode='rgb_array') and records to Rerun; "
    "there is no pygame window, no keyboard driving and one straight road segment"
)
CONFIG_KEYS: dict[str, str] = {
    **_DIRECT,
    "duration": "episode.max_decisions (duration x policy_frequency)",
    "simulation_frequency": "episode.physics_dt_s and frames_per_decision",
    "policy_frequency": "episode.frames_per_decision",
    "controlled_vehicles": "one controlled car (1)",
    "initial_lane_id": "a random lane (None)",
    "other_vehicles_type": "highway_env.vehicle.behavior.IDMVehicle",
    "observation": 'kinematics.* ({"type": "Kinematics", ...})',
    "action": 'highway_scene.target_speeds_mps ({"type": "DiscreteMetaAction", ...})',
    **VIEW_KEYS,
    **{key: "no effect here" for key in NO_EFFECT_KEYS},
}
OBSERVATION_KEYS = {
    "type": "Kinematics",
    "vehicles_count": "kinematics.vehicles_count",
    "features": "kinematics.features",
    "features_range": "kinematics.*_range_*",
    "absolute": "kinematics.absolute",
    "normalize": "kinematics.normalize",
    "clip": "kinematics.clip",
    "see_behind": "kinematics.see_behind",
    "order": "sorted",
}
ACTION_KEYS = {
    "type": "DiscreteMetaAction",
    "target_speeds": _SCENE + "target_speeds_mps",
    "longitudinal": "the actions: SLOWER, IDLE, FASTER (with lateral false)",
    "lateral": "the actions: LANE_LEFT, IDLE, LANE_RIGHT (with longitudinal false)",
}
_RANGE_SETTINGS = {
    "x": "kinematics.x_range_m",
    "y": "kinematics.y_range_m",
    "vx": "kinematics.vx_range_mps",
    "vy": "kinematics.vy_range_mps",
}
# The keys said as having no effect in this process so far (each is said once).
_SAID: set[str] = set()


@dataclass(frozen=True)
class HighwayEnvConfig:
    """A highway-env ``config`` read for a preset: overtake's settings, the action set (its
    labels in highway-env's numbers), how render() frames its picture, and the keys given
    that have no effect here."""

    overrides: dict[str, Any]
    actions: tuple[str, ...] = ACTION_LABELS
    view: PictureView = field(default_factory=PictureView)
    no_effect: tuple[str, ...] = ()
    # Each overtake setting set, named as the user gave it (config['lanes_count']), so that a
    # refused value is said in the user's words.
    given_as: dict[str, str] = field(default_factory=dict)

    @property
    def to_overtake(self) -> np.ndarray:
        """overtake's action for each of this set's numbers."""
        return np.array([OVERTAKE_ACTION[label] for label in self.actions], dtype=np.int64)

    def in_users_words(self, message: str) -> str:
        """A refusal naming overtake's setting, said with the key the user gave."""
        for setting in sorted(self.given_as, key=len, reverse=True):
            if message.startswith(setting + " "):
                return f"{self.given_as[setting]}{message[len(setting) :]} (overtake's {setting})"
            message = re.sub(
                rf"(?<![\w.]){re.escape(setting)}(?![\w.])",
                f"{self.given_as[setting]} ({setting})",
                message,
            )
        return message


def _refuse_unknown(given: Mapping[str, Any], known: Sequence[str], where: str) -> None:
    for key in given:
        if key not in known:
            near = difflib.get_close_matches(str(key), list(known), n=1)
            hint = f"; did you mean {near[0]!r}?" if near else ""
            raise BadConfig(
                f"{where}: unknown key {key!r}{hint} (the keys taken: {', '.join(known)})"
            )


def _require(key: str, value: Any, allowed: Any) -> None:
    if value != allowed:
        raise BadConfig(f"config[{key!r}] = {value!r} is not allowed: expected {allowed!r}")


def _mapping(where: str, value: Any) -> dict[str, Any]:
    if not isinstance(value, Mapping):
        raise BadConfig(f"{where} is a dict of highway-env's keys, got {value!r}")
    return dict(value)


def _number(key: str, value: Any, *, whole: bool = False, positive: bool = True) -> None:
    kinds = (int, np.integer) if whole else (int, float, np.integer, np.floating)
    ok = isinstance(value, kinds) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or (positive and value <= 0):
        wanted = "a positive " + ("integer" if whole else "number")
        raise BadConfig(f"config[{key!r}] = {value!r} is not allowed: expected {wanted}")


def _view(config: Mapping[str, Any]) -> PictureView:
    default = PictureView()
    width = config.get("screen_width", default.width_px)
    height = config.get("screen_height", default.height_px)
    scaling = config.get("scaling", default.pixels_per_m)
    centering = config.get("centering_position", default.centering)
    _number("screen_width", width, whole=True)
    _number("screen_height", height, whole=True)
    _number("scaling", scaling)
    if not (
        isinstance(centering, Sequence)
        and len(centering) == 2
        and all(isinstance(c, (int, float)) and math.isfinite(c) for c in centering)
    ):
        raise BadConfig(
            f"config['centering_position'] = {centering!r} is not allowed: expected a pair "
            "[x, y], fractions of the picture's width and height"
        )
    return PictureView(int(width), int(height), float(scaling), (centering[0], centering[1]))


def read_config(preset: str, config: Mapping[str, Any] | None) -> HighwayEnvConfig:
    """A highway-env ``config`` dict on ``preset`` (highway-fast or highway), read: raises
    BadConfig for an unknown key (naming the nearest) or a value these presets do not offer."""
    config = _mapping("config", config or {})
    _refuse_unknown(config, list(CONFIG_KEYS), "config")
    overrides: dict[str, Any] = {
        setting: config[key] for key, setting in _DIRECT.items() if key in config
    }
    given_as = {setting: f"config[{key!r}]" for key, setting in _DIRECT.items() if key in config}
    _require("controlled_vehicles", config.get("controlled_vehicles", 1), 1)
    _require("initial_lane_id", config.get("initial_lane_id"), None)
    _require(
        "other_vehicles_type",
        config.get("other_vehicles_type", CONFIG_KEYS["other_vehicles_type"]),
        CONFIG_KEYS["other_vehicles_type"],
    )
    default_hertz, default_duration = PRESET_TIMES[preset]
    policy = config.get("policy_frequency", 1)
    simulation = config.get("simulation_frequency", default_hertz * policy)
    if (
        not isinstance(policy, int)
        or not isinstance(simulation, int)
        or policy <= 0
        or simulation <= 0
        or simulation % policy
    ):
        raise BadConfig(
            "config: simulation_frequency must be a whole multiple of policy_frequency, "
            f"both positive integers (Hz), got {simulation!r} and {policy!r}"
        )
    overrides["episode.frames_per_decision"] = simulation // policy
    overrides["episode.physics_dt_s"] = 1.0 / simulation
    duration = config.get("duration", default_duration)
    _number("duration", duration)
    overrides["episode.max_decisions"] = round(duration * policy)
    given_as["episode.max_decisions"] = "config['duration'] x config['policy_frequency']"
    observation = _mapping("config['observation']", config.get("observation", {}))
    _refuse_unknown(observation, list(OBSERVATION_KEYS), "config['observation']")
    _require("observation.type", observation.get("type", "Kinematics"), "Kinematics")
    _require("observation.order", observation.get("order", "sorted"), "sorted")
    for key in ("vehicles_count", "features", "absolute", "normalize", "clip", "see_behind"):
        if key in observation:
            value = observation[key]
            if key == "features" and not isinstance(value, (list, tuple)):
                raise BadConfig(
                    f"config['observation']['features'] = {value!r} is not allowed: expected a "
                    "list of feature names"
                )
            overrides[OBSERVATION_KEYS[key]] = list(value) if key == "features" else value
            given_as[OBSERVATION_KEYS[key]] = f"config['observation'][{key!r}]"
    ranges = _mapping(
        "config['observation']['features_range']", observation.get("features_range") or {}
    )
    _refuse_unknown(ranges, list(_RANGE_SETTINGS), "config['observation']['features_range']")
    for feature, value in ranges.items():
        overrides[_RANGE_SETTINGS[feature]] = list(value)
        given_as[_RANGE_SETTINGS[feature]] = f"config['observation']['features_range'][{feature!r}]"
    action = _mapping("config['action']", config.get("action", {}))
    _refuse_unknown(action, list(ACTION_KEYS), "config['action']")
    _require("action.type", action.get("type", "DiscreteMetaAction"), "DiscreteMetaAction")
    if "target_speeds" in action:
        speeds = action["target_speeds"]
        if not isinstance(speeds, (list, tuple, np.ndarray)):
            raise BadConfig(
                f"config['action']['target_speeds'] = {speeds!r} is not allowed: expected a "
                "list of speeds (m/s), increasing"
            )
        overrides[ACTION_KEYS["target_speeds"]] = list(speeds)
        given_as[ACTION_KEYS["target_speeds"]] = "config['action']['target_speeds']"
    longitudinal, lateral = action.get("longitudinal", True), action.get("lateral", True)
    for key, value in (("longitudinal", longitudinal), ("lateral", lateral)):
        if not isinstance(value, bool):
            raise BadConfig(
                f"config['action'][{key!r}] = {value!r} is not allowed: expected true or false"
            )
    if not (longitudinal or lateral):
        raise BadConfig(
            "config['action']: longitudinal and lateral are both false, expected at least one "
            "of them true (as highway-env's DiscreteMetaAction)"
        )
    labels = (
        ACTION_LABELS
        if longitudinal and lateral
        else LONGITUDINAL_LABELS
        if longitudinal
        else LATERAL_LABELS
    )
    no_effect = tuple(
        key for key, default in NO_EFFECT_KEYS.items() if key in config and config[key] != default
    )
    return HighwayEnvConfig(overrides, labels, _view(config), no_effect, given_as)


def overrides_from_config(preset: str, config: Mapping[str, Any] | None) -> dict[str, Any]:
    """overtake's settings for a highway-env ``config`` dict on ``preset`` (highway-fast or
    highway): raises BadConfig for an unknown key (naming the nearest) or a value these
    presets do not offer."""
    return read_config(preset, config).overrides


def say_no_effect(keys: Sequence[str]) -> None:
    """Say, once in this process and in one line, that these keys change nothing here."""
    fresh = [key for key in keys if key not in _SAID]
    if fresh:
        _SAID.update(fresh)
        warnings.warn(
            f"config keys {', '.join(fresh)} have no effect here ({NO_EFFECT_WHY})",
            UserWarning,
            stacklevel=_callers_level(),
        )


def _callers_level() -> int:
    """The stack level of the first caller outside overtake and Gymnasium (the user's
    gym.make), where a warning is said."""
    level, frame = 2, sys._getframe(2)
    while frame.f_back is not None and str(frame.f_globals.get("__name__", "")).startswith(
        ("overtake.", "gymnasium.")
    ):
        level, frame = level + 1, frame.f_back
    return level
