"""``overtake/highway-fast-v0`` and ``overtake/highway-v0``: the presets ``highway-fast`` and
``highway`` as highway-env's own ids present them, so that a highway-env script changes its id
and nothing else; in process, or on a simulator server with ``connect=``, the same simulator
either way.

What a highway-env user's code reads is highway-env's: the observation is the Kinematics array
alone (not a dict), the actions are ``DiscreteMetaAction``'s numbers (0 LANE_LEFT, 1 IDLE, 2
LANE_RIGHT, 3 FASTER, 4 SLOWER; overtake's own order is keep, cruise up, cruise down, left,
right, and the ids translate; ``config["action"]`` may narrow them to highway-env's
longitudinal or lateral three), and ``config={...}`` takes highway-env's keys: the face reads
the action set, the picture's framing and the keys with no effect here
(:mod:`overtake.envs.highway_env_config`), and the simulator translates the rest into its
settings beside its scene (asked for by name in the open request, in process as on a
server); any other key is refused by name with the nearest known one suggested, and
``preset=`` is refused (the id names its scene). ``overrides=`` takes overtake's own settings
beyond them (dotted names, over ``config``'s, as docs/presets.md lists them: highway-env's
IDM car as the controlled car, for one). ``info`` holds overtake's entries (its action mask in
highway-env's order) and highway-env's ``speed`` (read from the observation's first row,
where it has vx and vy, scaled back by the ranges the observation's spec gives), ``crashed``
and ``rewards``.

The environment underneath is overtake's own, ``overtake/Highway-v0`` or, with ``connect``,
``overtake/RemoteHighway-v0``, made through Gymnasium's registry.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium import spaces

from overtake.protocol.errors import BadConfig
from overtake.protocol.specs import ObservationSpec

from .faces import NEXT_STEP
from .highway_env_config import (
    ACTION_LABELS,
    FROM_OVERTAKE,
    TO_OVERTAKE,
    HighwayEnvConfig,
    read_config,
    say_no_effect,
)
from .registry import HIGHWAY_ENV_ID, HIGHWAY_ENV_LIKE_IDS, REMOTE_HIGHWAY_ENV_ID

__all__ = [
    "ACTION_LABELS",
    "FROM_OVERTAKE",
    "TO_OVERTAKE",
    "HighwayEnvConfig",
    "HighwayEnvLike",
    "HighwayEnvLikeVector",
    "read_config",
]

# The observation these ids give: highway-env's Kinematics table.
KINEMATICS = "kinematics"


def _speed(obs: np.ndarray, spec: ObservationSpec) -> np.ndarray:
    """The cars' speed (m/s) from their rows' vx and vy, scaled back where the observation's
    spec says they are normalised; NaN where the observation has no vx or vy."""
    if "vx" not in spec.columns or "vy" not in spec.columns:
        return np.full(obs.shape[:-2], np.nan)
    parts = []
    for name in ("vx", "vy"):
        value = obs[..., 0, spec.columns.index(name)].astype(np.float64)
        scale = spec.scale(name)
        if scale is not None:
            value = (value + 1.0) / 2.0 * (scale.high - scale.low) + scale.low
        parts.append(value)
    return np.hypot(*parts)


def _highway_env_info(
    info: dict[str, Any], obs: np.ndarray, spec: ObservationSpec, to_overtake: np.ndarray
) -> dict[str, Any]:
    """highway-env's info entries beside overtake's, and overtake's action mask in
    highway-env's action order."""
    info["action_mask"] = np.asarray(info["action_mask"])[..., to_overtake]
    terms = info.get("reward_terms", {})
    speed = _speed(obs, spec)
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
    scene: str,
    config: Mapping[str, Any] | None,
    connect: str | Sequence[str] | None,
    preset: str | None,
    settings: Mapping[str, Any] | None,
    **kwargs: Any,
) -> tuple[str, dict[str, Any], HighwayEnvConfig]:
    """overtake's own environment for this configuration (its id, in process or remote, and
    keyword arguments: the scene's preset, the configuration for the simulator to translate,
    ``settings`` over it) and what the face reads of the configuration. ``settings``:
    overtake's own (dotted names, as ``overrides=`` of overtake/Highway-v0) over what
    ``config`` translates to, for what highway-env has no key for."""
    if scene not in HIGHWAY_ENV_LIKE_IDS.values():
        raise BadConfig(
            f"scene = {scene!r} is not one of highway-env's scenes here: expected one of "
            f"{', '.join(HIGHWAY_ENV_LIKE_IDS.values())}"
        )
    if preset is not None:
        raise BadConfig(
            f"preset={preset!r} is not taken by overtake/{scene}-v0, which is highway-env's "
            f"{scene}-v0 (the preset {scene}): choose the scene by its id, or overtake's "
            f"presets with gym.make('overtake/Highway-v0', preset={preset!r})"
        )
    read = read_config(config)
    made = {
        "preset": scene,
        "overrides": dict(settings or {}),
        "translation": read.translation,
        **kwargs,
    }
    if connect is not None:
        made["connect"] = connect
    env_id = HIGHWAY_ENV_ID if connect is None else REMOTE_HIGHWAY_ENV_ID
    say_no_effect(read.no_effect)
    return env_id, made, read


def _actions_text(labels: Sequence[str]) -> str:
    return ", ".join(f"{i} {label}" for i, label in enumerate(labels))


class HighwayEnvLike(gym.Env):
    """highway-env's ``highway-fast-v0`` / ``highway-v0`` interface over the preset."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 1}  # noqa: RUF012

    def __init__(
        self,
        scene: str = "highway-fast",
        config: Mapping[str, Any] | None = None,
        render_mode: str | None = None,
        connect: str | Sequence[str] | None = None,
        preset: str | None = None,
        overrides: Mapping[str, Any] | None = None,
    ) -> None:
        env_id, made, self.highway_env_config = _inner(
            scene, config, connect, preset, overrides, render_mode=render_mode
        )
        inner: Any = gym.make(env_id, **made).unwrapped
        self.env = inner
        self._kinematics = inner.behaviour_spec.observation(KINEMATICS)
        self.render_mode = render_mode
        self._to_overtake = self.highway_env_config.to_overtake
        self.observation_space = inner.observation_space[KINEMATICS]
        self.action_space = spaces.Discrete(len(self._to_overtake))
        self.metadata = {**self.metadata, **self.env.metadata}

    def _info(self, info: dict[str, Any], table: np.ndarray) -> dict[str, Any]:
        return _highway_env_info(info, table, self._kinematics, self._to_overtake)

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        obs, info = self.env.reset(seed=seed, options=options)
        table = obs[KINEMATICS]
        return table, self._info(info, table)

    def step(self, action):
        if not self.action_space.contains(action):
            labels = self.highway_env_config.actions
            raise ValueError(
                f"expected an action in [0, {len(labels)}) ({_actions_text(labels)}), "
                f"got {action!r}"
            )
        obs, reward, terminated, truncated, info = self.env.step(
            int(self._to_overtake[int(action)])
        )
        table = obs[KINEMATICS]
        return table, reward, terminated, truncated, self._info(info, table)

    def render(self) -> np.ndarray | None:  # type: ignore[override, unused-ignore]
        """The road from above (render_mode="rgb_array"), framed as highway-env's viewer frames
        it: config's screen_width x screen_height pixels at scaling pixels a metre, the car at
        centering_position."""
        road = self.env.simulator.road
        if self.render_mode != "rgb_array" or road is None:
            return None
        picture: np.ndarray = road.picture(0, self.highway_env_config.view)
        return picture

    def close(self) -> None:
        self.env.close()


class HighwayEnvLikeVector(gym.vector.VectorEnv):
    """``gym.make_vec`` of these ids: ``num_envs`` arenas in one pass, next-step autoreset."""

    metadata = {"render_modes": ["rgb_array"], "autoreset_mode": NEXT_STEP}  # noqa: RUF012

    def __init__(
        self,
        num_envs: int = 1,
        scene: str = "highway-fast",
        config: Mapping[str, Any] | None = None,
        render_mode: str | None = None,
        connect: str | Sequence[str] | None = None,
        preset: str | None = None,
        overrides: Mapping[str, Any] | None = None,
    ) -> None:
        env_id, made, self.highway_env_config = _inner(
            scene, config, connect, preset, overrides, render_mode=render_mode
        )
        inner: Any = gym.make_vec(
            env_id, num_envs=num_envs, vectorization_mode="vector_entry_point", **made
        )
        self.env = inner
        self._kinematics = inner.behaviour_spec.observation(KINEMATICS)
        self.num_envs, self.render_mode = num_envs, render_mode
        self._to_overtake = self.highway_env_config.to_overtake
        count = len(self._to_overtake)
        self.single_observation_space = inner.single_observation_space[KINEMATICS]
        self.single_action_space = spaces.Discrete(count)
        self.observation_space = gym.vector.utils.batch_space(
            self.single_observation_space, num_envs
        )
        self.action_space = spaces.MultiDiscrete(np.full(num_envs, count))

    def _info(self, info: dict[str, Any], table: np.ndarray) -> dict[str, Any]:
        return _highway_env_info(info, table, self._kinematics, self._to_overtake)

    def reset(self, *, seed: int | Sequence[int | None] | None = None, options=None):
        obs, info = self.env.reset(seed=seed, options=options)
        table = obs[KINEMATICS]
        return table, self._info(info, table)

    def step(self, actions):
        actions = np.asarray(actions)
        count = len(self._to_overtake)
        # Integers in range, checked without np.isin (a few per cent of a 64-arena step).
        if (
            actions.shape != (self.num_envs,)
            or actions.dtype.kind not in "iu"
            or actions.min() < 0
            or actions.max() >= count
        ):
            raise ValueError(
                f"expected {self.num_envs} actions in [0, {count}) "
                f"({_actions_text(self.highway_env_config.actions)}), got {actions!r}"
            )
        obs, reward, terminated, truncated, info = self.env.step(self._to_overtake[actions])
        table = obs[KINEMATICS]
        return table, reward, terminated, truncated, self._info(info, table)

    def render(self):  # type: ignore[override, unused-ignore]
        """Each road from above (render_mode="rgb_array"), framed as highway-env's viewer
        frames it (see HighwayEnvLike.render)."""
        road = self.env.simulator.road
        if self.render_mode != "rgb_array" or road is None:
            return None
        view = self.highway_env_config.view
        return tuple(road.picture(i, view) for i in range(self.num_envs))

    def close_extras(self, **kwargs: Any) -> None:
        # A refused configuration leaves no environment underneath to close (and Gymnasium's
        # __del__ closes what __init__ left).
        env = getattr(self, "env", None)
        if env is not None:
            env.close()
