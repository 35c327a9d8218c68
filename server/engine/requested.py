"""The simulator an open request asks for: a preset with overrides (over a configuration in
another simulator's words, OpenRequest.translation, translated by :mod:`.sim.translations`),
or, with a record's configuration (OpenRequest.as_recorded), the simulator that record was
made on, built again from the server's settings' history (:mod:`.sim.settings_history`); the
ego fields and observations the trainer reads. The in-process environments ask here too, so a
request means one simulator wherever it runs. What cannot be built is refused with the
protocol's errors (an unknown preset, a bad configuration), naming why."""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any

from overtake.protocol import errors
from overtake.protocol.messages import Scalar, Translation

from ..sim import PRESETS, ConfigError, SimConfig, settings_history
from ..sim.config import Translated
from ..sim.translations import translate


def resolve_config(
    preset: str,
    overrides: Mapping[str, Scalar],
    as_recorded: str = "",
    observations: tuple[str, ...] = (),
    ego_fields: tuple[str, ...] = (),
    translation: Translation | None = None,
) -> SimConfig:
    """The simulator a request asks for: ``preset`` with ``translation``'s settings and
    ``overrides`` over them, or, with ``as_recorded`` (a record's configuration as JSON), the
    one that record was made on; ``ego_fields`` and ``observations`` what the trainer reads
    (:func:`~.sim.settings_history.requested_config`), refused with the protocol's errors."""
    if preset not in PRESETS:
        raise errors.UnknownPreset(
            f"unknown preset {preset!r}: this server has {', '.join(sorted(PRESETS))}"
        )
    try:
        recorded = _record_config(as_recorded) if as_recorded else None
        return settings_history.requested_config(
            preset, overrides, recorded, observations, ego_fields, translated(preset, translation)
        )
    except ConfigError as error:
        raise errors.BadConfig(str(error)) from None


def translated(preset: str, translation: Translation | None) -> Translated | None:
    """``translation``'s configuration for ``preset`` as the simulator's settings (None:
    none asked for); :class:`ConfigError` where the translation refuses it."""
    if translation is None:
        return None
    return translate(translation.source, preset, translation.config_json)


def _record_config(text: str) -> dict[str, Any]:
    try:
        config = json.loads(text)
    except ValueError as error:
        raise errors.BadConfig(f"as_recorded is not JSON ({error})") from None
    if not isinstance(config, dict):
        raise errors.BadConfig(
            f"as_recorded is a record's configuration (a JSON object), got {type(config).__name__}"
        )
    return config
