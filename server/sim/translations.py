"""Configurations written in another simulator's words, translated into this simulator's
settings by the translation's name (``OpenRequest.translation``, protocol 1.11): each lives
beside the scene it configures (highway-env's: :mod:`.highway_scene.highway_env_config`), and
the in-process environments and the server both translate here, so that a configuration
means one simulator wherever it runs."""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from typing import Any

from overtake.protocol.vocabulary import HIGHWAY_ENV_TRANSLATION

from .config import ConfigError, SimConfig, Translated
from .highway_scene.highway_env_config import translate_highway_env
from .presets import make_config

# Each translation by the name a request gives it: (the preset's configuration, the
# configuration as the other simulator takes it) -> this simulator's settings.
TRANSLATORS: dict[str, Callable[[SimConfig, Mapping[str, Any]], Translated]] = {
    HIGHWAY_ENV_TRANSLATION: translate_highway_env,
}


def translate(source: str, preset: str, config_json: str) -> Translated:
    """``config_json`` (a JSON object in ``source``'s words) for ``preset``, as this simulator's
    settings: :class:`ConfigError` naming what is wrong (an unknown translation or preset, a
    key or value the translation does not take)."""
    translator = TRANSLATORS.get(source)
    if translator is None:
        raise ConfigError(
            f"unknown translation {source!r}: expected one of {', '.join(TRANSLATORS)}"
        )
    try:
        config = json.loads(config_json)
    except ValueError as error:
        raise ConfigError(f"the {source} configuration is not JSON ({error})") from None
    if not isinstance(config, dict):
        raise ConfigError(
            f"the {source} configuration is a dict of its keys, got {type(config).__name__}"
        )
    return translator(make_config(preset), config)
