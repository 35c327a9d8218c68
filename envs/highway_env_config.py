"""What highway-env's face (:mod:`overtake.envs.highway_env_like`) reads of a highway-env
``config`` dict itself, and how it asks the simulator for the rest.

The face reads highway-env's action order (its ``DiscreteMetaAction`` numbers, and the
subsets ``config["action"]``'s ``longitudinal`` and ``lateral`` keep), the viewer's keys that
frame ``render()``'s picture, and the keys that change nothing here (said once, in one line).
Everything else of ``config`` is the simulator's: the whole dict travels, in highway-env's
words, in the open request (:class:`~overtake.protocol.messages.Translation`, protocol 1.11),
and the simulator translates it beside its scene (``server/sim/highway_scene/``), in process
as on a server, refusing an unknown key by name with the nearest known one suggested and a
refused value in the user's words. Every refusal is a
:class:`~overtake.protocol.errors.BadConfig` (a ``ValueError``).
"""

from __future__ import annotations

import json
import math
import sys
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from overtake.protocol.errors import BadConfig
from overtake.protocol.messages import Translation
from overtake.protocol.vocabulary import HIGHWAY_ENV_TRANSLATION

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
# The keys above and config["action"]'s longitudinal and lateral are the contract's
# HIGHWAY_ENV_FACE_KEYS and HIGHWAY_ENV_FACE_ACTION_KEYS, which the simulator's translation
# leaves to this face (tests/envs/test_highway_env_like.py holds them to each other).
# The keys said as having no effect in this process so far (each is said once).
_SAID: set[str] = set()


@dataclass(frozen=True)
class HighwayEnvConfig:
    """A highway-env ``config`` as the face reads it: the action set (its labels in
    highway-env's numbers), how render() frames its picture, the keys given that have no
    effect here, and the whole configuration as the simulator is asked to translate it."""

    translation: Translation
    actions: tuple[str, ...] = ACTION_LABELS
    view: PictureView = field(default_factory=PictureView)
    no_effect: tuple[str, ...] = ()

    @property
    def to_overtake(self) -> np.ndarray:
        """overtake's action for each of this set's numbers."""
        return np.array([OVERTAKE_ACTION[label] for label in self.actions], dtype=np.int64)


def _mapping(where: str, value: Any) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise BadConfig(f"{where} is a dict of highway-env's keys, got {value!r}")
    return value


def _number(key: str, value: Any, *, whole: bool = False) -> None:
    kinds = (int, np.integer) if whole else (int, float, np.integer, np.floating)
    ok = isinstance(value, kinds) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or value <= 0:
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


def _actions(config: Mapping[str, Any]) -> tuple[str, ...]:
    """The action set config["action"] keeps, in highway-env's numbers."""
    action = _mapping("config['action']", config.get("action", {}))
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
    if longitudinal and lateral:
        return ACTION_LABELS
    return LONGITUDINAL_LABELS if longitudinal else LATERAL_LABELS


def _as_json(value: Any) -> Any:
    """numpy's values as JSON's (a script may give target speeds as an array)."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"{type(value).__name__} {value!r}")


def translation_request(config: Mapping[str, Any]) -> Translation:
    """``config`` as the simulator is asked to translate it: highway-env's words, as JSON."""
    try:
        text = json.dumps(dict(config), default=_as_json)
    except (TypeError, ValueError) as error:
        raise BadConfig(
            f"config holds a value that is not a number, text, list or dict ({error}): "
            "expected highway-env's plain values"
        ) from None
    return Translation(source=HIGHWAY_ENV_TRANSLATION, config_json=text)


def read_config(config: Mapping[str, Any] | None) -> HighwayEnvConfig:
    """What the face reads of a highway-env ``config`` (the action set, the picture's
    framing, the keys with no effect here), and the request that asks the simulator for the
    rest; raises BadConfig for a value of the face's keys that highway-env does not take."""
    config = _mapping("config", config or {})
    no_effect = tuple(
        key for key, default in NO_EFFECT_KEYS.items() if key in config and config[key] != default
    )
    return HighwayEnvConfig(translation_request(config), _actions(config), _view(config), no_effect)


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
