"""``overtake/highway-fast-v0`` and ``overtake/highway-v0``: the presets ``highway-fast`` and
``highway`` as highway-env's own ids present them, so that a highway-env script changes its id
and nothing else; in process, or on a simulator server with ``connect=``.

What a highway-env user's code reads is highway-env's: the observation is the Kinematics array
alone (not a dict), the actions are ``DiscreteMetaAction``'s numbers (0 LANE_LEFT, 1 IDLE, 2
LANE_RIGHT, 3 FASTER, 4 SLOWER; overtake's own order is keep, cruise up, cruise down, left,
right, and the ids translate), and ``config={...}`` takes highway-env's keys, those the presets
honour (:data:`CONFIG_KEYS`), each turned into overtake's settings; any other key is refused by
name with the nearest known one suggested. ``info`` holds overtake's entries (its action mask
in highway-env's order) and highway-env's ``speed`` (read from the observation's first row,
where it has vx and vy), ``crashed`` and ``rewards``.

The environment underneath is overtake's own, ``overtake/Highway-v0`` or, with ``connect``,
``overtake/RemoteHighway-v0``, made through Gymnasium's registry. Over the wire a setting is a
single value: the observation's ``features`` and ``features_range`` are taken in process only.
"""

from __future__ import annotations

import difflib
from collections.abc import Mapping, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from overtake.protocol.errors import BadConfig

from .faces import NEXT_STEP
from .registry import HIGHWAY_ENV_ID, REMOTE_HIGHWAY_ENV_ID

# highway-env's DiscreteMetaAction numbers -> overtake's (keep 0, cruise up 1, cruise down 2,
# lane left 3, lane right 4), and back.
TO_OVERTAKE = np.array([3, 0, 4, 1, 2], dtype=np.int64)
FROM_OVERTAKE = np.argsort(TO_OVERTAKE)
ACTION_LABELS = ("LANE_LEFT", "IDLE", "LANE_RIGHT", "FASTER", "SLOWER")

# Each preset's physics frames a second and episode length in seconds, at a decision a second
# (server/sim/highway_scene/presets.py, from highway-env's configurations).
PRESET_TIMES = {"highway-fast": (5, 30), "highway": (15, 40)}

# highway-env's keys these ids take, each with overtake's setting (or how it maps).
_SCENE = "highway_scene."
CONFIG_KEYS: dict[str, str] = {
    "lanes_count": "road.lane_count",
    "vehicles_count": "traffic.vehicle_count",
    "vehicles_density": _SCENE + "vehicles_density",
    "ego_spacing": _SCENE + "ego_spacing",
    "duration": "episode.max_decisions (duration x policy_frequency)",
    "simulation_frequency": "episode.physics_dt_s and frames_per_decision",
    "policy_frequency": "episode.frames_per_decision",
    "collision_reward": _SCENE + "collision_reward",
    "right_lane_reward": _SCENE + "right_lane_reward",
    "high_speed_reward": _SCENE + "high_speed_reward",
    "lane_change_reward": _SCENE + "lane_change_reward",
    "reward_speed_range": _SCENE + "reward_speed_range_mps",
    "normalize_reward": _SCENE + "normalize_reward",
    "offroad_terminal": _SCENE + "offroad_terminal",
    "controlled_vehicles": "one controlled car (1)",
    "initial_lane_id": "a random lane (None)",
    "other_vehicles_type": "highway_env.vehicle.behavior.IDMVehicle",
    "observation": 'kinematics.* ({"type": "Kinematics", ...})',
    "action": 'highway_scene.target_speeds_mps ({"type": "DiscreteMetaAction", ...})',
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
ACTION_KEYS = {"type": "DiscreteMetaAction", "target_speeds": _SCENE + "target_speeds_mps"}
_RANGE_SETTINGS = {
    "x": "kinematics.x_range_m",
    "y": "kinematics.y_range_m",
    "vx": "kinematics.vx_range_mps",
    "vy": "kinematics.vy_range_mps",
}
_DIRECT = {key: value for key, value in CONFIG_KEYS.items() if value.startswith(_SCENE)} | {
    "lanes_count": "road.lane_count",
    "vehicles_count": "traffic.vehicle_count",
}


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


def overrides_from_config(preset: str, config: Mapping[str, Any] | None) -> dict[str, Any]:
    """overtake's settings for a highway-env ``config`` dict on ``preset`` (highway-fast or
    highway): raises BadConfig for an unknown key (naming the nearest) or a value these
    presets do not offer."""
    config = dict(config or {})
    _refuse_unknown(config, list(CONFIG_KEYS), "config")
    overrides: dict[str, Any] = {
        setting: config[key] for key, setting in _DIRECT.items() if key in config
    }
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
    if not isinstance(policy, int) or not isinstance(simulation, int) or simulation % policy:
        raise BadConfig(
            "config: simulation_frequency must be a whole multiple of policy_frequency, "
            f"both integers (Hz), got {simulation!r} and {policy!r}"
        )
    overrides["episode.frames_per_decision"] = simulation // policy
    overrides["episode.physics_dt_s"] = 1.0 / simulation
    duration = config.get("duration", default_duration)
    overrides["episode.max_decisions"] = round(duration * policy)
    observation = dict(config.get("observation", {"type": "Kinematics"}))
    _refuse_unknown(observation, list(OBSERVATION_KEYS), "config['observation']")
    _require("observation.type", observation.get("type", "Kinematics"), "Kinematics")
    _require("observation.order", observation.get("order", "sorted"), "sorted")
    for key in ("vehicles_count", "features", "absolute", "normalize", "clip", "see_behind"):
        if key in observation:
            value = observation[key]
            overrides[OBSERVATION_KEYS[key]] = list(value) if key == "features" else value
    ranges = dict(observation.get("features_range") or {})
    _refuse_unknown(ranges, list(_RANGE_SETTINGS), "config['observation']['features_range']")
    for feature, value in ranges.items():
        overrides[_RANGE_SETTINGS[feature]] = list(value)
    action = dict(config.get("action", {"type": "DiscreteMetaAction"}))
    _refuse_unknown(action, list(ACTION_KEYS), "config['action']")
    _require("action.type", action.get("type", "DiscreteMetaAction"), "DiscreteMetaAction")
    if "target_speeds" in action:
        overrides[ACTION_KEYS["target_speeds"]] = [float(s) for s in action["target_speeds"]]
    return overrides


def _speed(obs: np.ndarray, features: Sequence[str], ranges: Mapping[str, Any]) -> np.ndarray:
    """The cars' speed (m/s) from their rows' vx and vy (normalised by ``ranges`` where the
    observation is); NaN where the features have no vx or vy."""
    if "vx" not in features or "vy" not in features:
        return np.full(obs.shape[:-2], np.nan)
    parts = []
    for name in ("vx", "vy"):
        value = obs[..., 0, list(features).index(name)].astype(np.float64)
        low, high = ranges.get(name, (-80.0, 80.0))
        if ranges.get("normalize", True):
            value = (value + 1.0) / 2.0 * (high - low) + low
        parts.append(value)
    return np.hypot(*parts)


def _highway_env_info(info: dict[str, Any], obs: np.ndarray, features, ranges) -> dict[str, Any]:
    """highway-env's info entries beside overtake's, and overtake's action mask in
    highway-env's action order."""
    info["action_mask"] = np.asarray(info["action_mask"])[..., TO_OVERTAKE]
    terms = info.get("reward_terms", {})
    speed = _speed(obs, features, ranges)
    info["speed"] = float(speed) if np.ndim(speed) == 0 else speed
    collision = np.asarray(terms.get("collision", 0.0)) > 0
    info["crashed"] = bool(collision) if np.ndim(collision) == 0 else collision
    info["rewards"] = {
        f"{name}_reward": value for name, value in terms.items() if name != "on_road"
    } | {"on_road_reward": terms.get("on_road")}
    return info


# ``connect``: one endpoint or several (overtake.ipc.transport.Endpoints, spelled out here:
# envs imports the contract only).
def _inner(
    preset: str,
    config: Mapping[str, Any] | None,
    connect: str | Sequence[str] | None,
    **kwargs: Any,
) -> tuple[str, dict[str, Any], Sequence[str], dict[str, Any]]:
    """overtake's own environment for this configuration (its id, in process or remote, and
    keyword arguments), and the observation's features and normalisation (for the speed in
    info)."""
    overrides = overrides_from_config(preset, config)
    features = overrides.get("kinematics.features", ["presence", "x", "y", "vx", "vy"])
    ranges = {
        "vx": overrides.get("kinematics.vx_range_mps", (-80.0, 80.0)),
        "vy": overrides.get("kinematics.vy_range_mps", (-80.0, 80.0)),
        "normalize": overrides.get("kinematics.normalize", True),
    }
    made = {"preset": preset, "overrides": overrides, **kwargs}
    if connect is not None:
        made["connect"] = connect
    env_id = HIGHWAY_ENV_ID if connect is None else REMOTE_HIGHWAY_ENV_ID
    return env_id, made, features, ranges


class HighwayEnvLike(gym.Env):
    """highway-env's ``highway-fast-v0`` / ``highway-v0`` interface over the preset."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 1}  # noqa: RUF012

    def __init__(
        self,
        preset: str = "highway-fast",
        config: Mapping[str, Any] | None = None,
        render_mode: str | None = None,
        connect: str | Sequence[str] | None = None,
    ) -> None:
        env_id, made, self._features, self._ranges = _inner(
            preset, config, connect, render_mode=render_mode
        )
        self.env: Any = gym.make(env_id, **made).unwrapped
        self.render_mode = render_mode
        self.observation_space = self.env.observation_space["kinematics"]  # type: ignore[index]
        self.action_space = spaces.Discrete(len(ACTION_LABELS))
        self.metadata = {**self.metadata, **self.env.metadata}

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        obs, info = self.env.reset(seed=seed, options=options)
        table = obs["kinematics"]
        return table, _highway_env_info(info, table, self._features, self._ranges)

    def step(self, action):
        if not self.action_space.contains(action):
            raise ValueError(
                f"expected an action in [0, 5) ({', '.join(ACTION_LABELS)}), got {action!r}"
            )
        obs, reward, terminated, truncated, info = self.env.step(int(TO_OVERTAKE[int(action)]))
        table = obs["kinematics"]
        info = _highway_env_info(info, table, self._features, self._ranges)
        return table, reward, terminated, truncated, info

    def render(self) -> np.ndarray | None:  # type: ignore[override, unused-ignore]
        return self.env.render()

    def close(self) -> None:
        self.env.close()


class HighwayEnvLikeVector(gym.vector.VectorEnv):
    """``gym.make_vec`` of these ids: ``num_envs`` arenas in one pass, next-step autoreset."""

    metadata = {"render_modes": ["rgb_array"], "autoreset_mode": NEXT_STEP}  # noqa: RUF012

    def __init__(
        self,
        num_envs: int = 1,
        preset: str = "highway-fast",
        config: Mapping[str, Any] | None = None,
        render_mode: str | None = None,
        connect: str | Sequence[str] | None = None,
    ) -> None:
        env_id, made, self._features, self._ranges = _inner(
            preset, config, connect, render_mode=render_mode
        )
        self.env: Any = gym.make_vec(
            env_id, num_envs=num_envs, vectorization_mode="vector_entry_point", **made
        )
        self.num_envs, self.render_mode = num_envs, render_mode
        self.single_observation_space = self.env.single_observation_space["kinematics"]  # type: ignore[index]
        self.single_action_space = spaces.Discrete(len(ACTION_LABELS))
        self.observation_space = gym.vector.utils.batch_space(
            self.single_observation_space, num_envs
        )
        self.action_space = spaces.MultiDiscrete(np.full(num_envs, len(ACTION_LABELS)))

    def reset(self, *, seed: int | Sequence[int | None] | None = None, options=None):
        obs, info = self.env.reset(seed=seed, options=options)
        table = obs["kinematics"]
        return table, _highway_env_info(info, table, self._features, self._ranges)

    def step(self, actions):
        actions = np.asarray(actions)
        # Integers in range, checked without np.isin (a few per cent of a 64-arena step).
        if (
            actions.shape != (self.num_envs,)
            or actions.dtype.kind not in "iu"
            or actions.min() < 0
            or actions.max() >= len(ACTION_LABELS)
        ):
            raise ValueError(
                f"expected {self.num_envs} actions in [0, 5) ({', '.join(ACTION_LABELS)}), "
                f"got {actions!r}"
            )
        obs, reward, terminated, truncated, info = self.env.step(TO_OVERTAKE[actions])
        table = obs["kinematics"]
        info = _highway_env_info(info, table, self._features, self._ranges)
        return table, reward, terminated, truncated, info

    def render(self):  # type: ignore[override, unused-ignore]
        return self.env.render()

    def close_extras(self, **kwargs: Any) -> None:
        self.env.close()
