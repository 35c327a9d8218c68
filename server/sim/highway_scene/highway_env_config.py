"""highway-env's ``config`` dict translated into the simulator's settings, beside the scene it
configures: the presets ``highway-fast`` and ``highway`` (:mod:`.presets`) as highway-env's
``highway-fast-v0`` and ``highway-v0``.

A trainer asks for this translation by name (``OpenRequest.translation``, protocol 1.11; the
in-process environment builds the same request), so that ``config={...}`` means the same
simulator in process and on any server. Each key highway-env's scenes take is turned into
settings here, or is one the face reads itself (the viewer's framing, the action subset and
the keys that change nothing here: :data:`~overtake.protocol.vocabulary.HIGHWAY_ENV_FACE_KEYS`,
left alone); any other key is refused by name with the nearest known one suggested, and a
refused value is said with the key the user gave (:meth:`.Translated.in_users_words`). Every
refusal is a :class:`~overtake.protocol.errors.BadConfig`.

The defaults that depend on the scene (its frames a second, its episode's length) are read
from the preset's own configuration, not copied here.
"""

from __future__ import annotations

import difflib
import math
from collections.abc import Mapping, Sequence
from typing import Any

from overtake.protocol.vocabulary import (
    HIGHWAY_ENV_FACE_ACTION_KEYS,
    HIGHWAY_ENV_FACE_KEYS,
    HIGHWAY_SCENE_PRESETS,
)

from ..config import ConfigError, PlainValue, SimConfig, Translated
from ..presets import make_config

# highway-env's keys that are one setting each here.
DIRECT_SETTINGS: dict[str, str] = {
    "lanes_count": "road.lane_count",
    "vehicles_count": "traffic.vehicle_count",
    "vehicles_density": "highway_scene.vehicles_density",
    "ego_spacing": "highway_scene.ego_spacing",
    "collision_reward": "highway_scene.collision_reward",
    "right_lane_reward": "highway_scene.right_lane_reward",
    "high_speed_reward": "highway_scene.high_speed_reward",
    "lane_change_reward": "highway_scene.lane_change_reward",
    "reward_speed_range": "highway_scene.reward_speed_range_mps",
    "normalize_reward": "highway_scene.normalize_reward",
    "offroad_terminal": "highway_scene.offroad_terminal",
}
# The only value these scenes take for a key (highway-env's default).
OTHER_VEHICLES_TYPE = "highway_env.vehicle.behavior.IDMVehicle"
# Every top-level key taken, with what it becomes here.
CONFIG_KEYS: dict[str, str] = {
    **DIRECT_SETTINGS,
    "duration": "episode.max_decisions (duration x policy_frequency)",
    "simulation_frequency": "episode.physics_dt_s and frames_per_decision",
    "policy_frequency": "episode.frames_per_decision",
    "controlled_vehicles": "one controlled car (1)",
    "initial_lane_id": "a random lane (None)",
    "other_vehicles_type": OTHER_VEHICLES_TYPE,
    "observation": 'kinematics.* ({"type": "Kinematics", ...})',
    "action": 'highway_scene.target_speeds_mps ({"type": "DiscreteMetaAction", ...})',
    **{key: "read by the environment's face" for key in HIGHWAY_ENV_FACE_KEYS},
}
# config["observation"]'s keys: the Kinematics observation's settings.
OBSERVATION_SETTINGS: dict[str, str] = {
    "vehicles_count": "kinematics.vehicles_count",
    "features": "kinematics.features",
    "absolute": "kinematics.absolute",
    "normalize": "kinematics.normalize",
    "clip": "kinematics.clip",
    "see_behind": "kinematics.see_behind",
}
OBSERVATION_KEYS: tuple[str, ...] = ("type", *OBSERVATION_SETTINGS, "features_range", "order")
# config["observation"]["features_range"]'s keys, each feature's range here.
RANGE_SETTINGS: dict[str, str] = {
    "x": "kinematics.x_range_m",
    "y": "kinematics.y_range_m",
    "vx": "kinematics.vx_range_mps",
    "vy": "kinematics.vy_range_mps",
}
TARGET_SPEEDS_SETTING = "highway_scene.target_speeds_mps"
ACTION_KEYS: tuple[str, ...] = ("type", "target_speeds", *HIGHWAY_ENV_FACE_ACTION_KEYS)


def _refuse_unknown(given: Mapping[str, Any], known: Sequence[str], where: str) -> None:
    for key in given:
        if key not in known:
            near = difflib.get_close_matches(str(key), list(known), n=1)
            hint = f"; did you mean {near[0]!r}?" if near else ""
            raise ConfigError(
                f"{where}: unknown key {key!r}{hint} (the keys taken: {', '.join(known)})"
            )


def _require(key: str, value: Any, allowed: Any) -> None:
    if value != allowed:
        raise ConfigError(f"config[{key!r}] = {value!r} is not allowed: expected {allowed!r}")


def _mapping(where: str, value: Any) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise ConfigError(f"{where} is a dict of highway-env's keys, got {value!r}")
    return value


def _list(where: str, value: Any, expected: str) -> list[Any]:
    # JSON has no tuples: a list or a tuple (in process) is a list of values.
    if not isinstance(value, (list, tuple)):
        raise ConfigError(f"{where} = {value!r} is not allowed: expected {expected}")
    return list(value)


def _frequencies(config: Mapping[str, Any], preset: SimConfig) -> tuple[int, int]:
    """(simulation, policy) frequencies in Hz: the policy's a decision a second unless given,
    the simulation's the preset's frames a decision at that rate unless given (highway-env's
    scenes decide once a second: their frames a decision are their simulation_frequency)."""
    policy: Any = config.get("policy_frequency", 1)
    simulation: Any = config.get("simulation_frequency")
    if simulation is None and isinstance(policy, int):
        simulation = preset.episode.frames_per_decision * policy
    whole = all(isinstance(v, int) and not isinstance(v, bool) for v in (policy, simulation))
    if not whole or policy <= 0 or simulation <= 0 or simulation % policy:
        raise ConfigError(
            "config: simulation_frequency must be a whole multiple of policy_frequency, "
            f"both positive integers (Hz), got {simulation!r} and {policy!r}"
        )
    return simulation, policy


def translate_highway_env(preset: SimConfig, config: Mapping[str, Any]) -> Translated:
    """highway-env's ``config`` for ``preset`` (highway-fast or highway) as this simulator's
    settings: :class:`ConfigError` for an unknown key (naming the nearest) or a value these
    scenes do not offer."""
    if preset.preset not in HIGHWAY_SCENE_PRESETS:
        raise ConfigError(
            f"highway-env's config is translated for its scenes, the presets "
            f"{', '.join(HIGHWAY_SCENE_PRESETS)}, not preset {preset.preset}"
        )
    config = _mapping("config", config)
    _refuse_unknown(config, list(CONFIG_KEYS), "config")
    overrides: dict[str, PlainValue] = {
        setting: config[key] for key, setting in DIRECT_SETTINGS.items() if key in config
    }
    given_as = {
        setting: f"config[{key!r}]" for key, setting in DIRECT_SETTINGS.items() if key in config
    }
    _require("controlled_vehicles", config.get("controlled_vehicles", 1), 1)
    _require("initial_lane_id", config.get("initial_lane_id"), None)
    _require(
        "other_vehicles_type",
        config.get("other_vehicles_type", OTHER_VEHICLES_TYPE),
        OTHER_VEHICLES_TYPE,
    )
    simulation, policy = _frequencies(config, preset)
    overrides["episode.frames_per_decision"] = simulation // policy
    overrides["episode.physics_dt_s"] = 1.0 / simulation
    default_duration_s = preset.episode.max_decisions * preset.episode.decision_period_s
    duration = config.get("duration", round(default_duration_s))
    ok = isinstance(duration, (int, float)) and not isinstance(duration, bool)
    if not ok or not math.isfinite(duration) or duration <= 0:
        raise ConfigError(
            f"config['duration'] = {duration!r} is not allowed: expected a positive number"
        )
    overrides["episode.max_decisions"] = round(duration * policy)
    given_as["episode.max_decisions"] = "config['duration'] x config['policy_frequency']"

    observation = _mapping("config['observation']", config.get("observation", {}))
    _refuse_unknown(observation, OBSERVATION_KEYS, "config['observation']")
    _require("observation.type", observation.get("type", "Kinematics"), "Kinematics")
    _require("observation.order", observation.get("order", "sorted"), "sorted")
    for key, setting in OBSERVATION_SETTINGS.items():
        if key in observation:
            where = f"config['observation'][{key!r}]"
            value = observation[key]
            if key == "features":
                value = _list(where, value, "a list of feature names")
            overrides[setting] = value
            given_as[setting] = where
    ranges = _mapping(
        "config['observation']['features_range']", observation.get("features_range") or {}
    )
    _refuse_unknown(ranges, list(RANGE_SETTINGS), "config['observation']['features_range']")
    for feature, value in ranges.items():
        where = f"config['observation']['features_range'][{feature!r}]"
        overrides[RANGE_SETTINGS[feature]] = _list(where, value, "a pair [low, high]")
        given_as[RANGE_SETTINGS[feature]] = where

    action = _mapping("config['action']", config.get("action", {}))
    _refuse_unknown(action, ACTION_KEYS, "config['action']")
    _require("action.type", action.get("type", "DiscreteMetaAction"), "DiscreteMetaAction")
    if "target_speeds" in action:
        where = "config['action']['target_speeds']"
        overrides[TARGET_SPEEDS_SETTING] = _list(
            where, action["target_speeds"], "a list of speeds (m/s), increasing"
        )
        given_as[TARGET_SPEEDS_SETTING] = where
    return Translated(overrides, given_as)


def overrides_from_config(preset: str, config: Mapping[str, Any]) -> dict[str, PlainValue]:
    """The settings highway-env's ``config`` stands for on ``preset`` (highway-fast or
    highway), as :func:`translate_highway_env` translates them."""
    return dict(translate_highway_env(make_config(preset), config).overrides)
