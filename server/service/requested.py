"""The simulator an open request asks for: a preset with overrides, or, with a record's
configuration (OpenRequest.as_recorded), the simulator that record was made on, built again
from the server's settings' history (:mod:`.sim.settings_history`). What cannot be built is
refused with the protocol's errors (an unknown preset, a bad configuration), naming why."""

from __future__ import annotations

import json
from collections.abc import Mapping
from typing import Any

from overtake.protocol import errors
from overtake.protocol.messages import Scalar

from ..sim import PRESETS, ConfigError, SimConfig, settings_history


def resolve_config(
    preset: str,
    overrides: Mapping[str, Scalar],
    as_recorded: str = "",
    observations: tuple[str, ...] = (),
) -> SimConfig:
    """The simulator a request asks for: ``preset`` with ``overrides``, or, with
    ``as_recorded`` (a record's configuration as JSON), the one that record was made on
    (:func:`~.sim.settings_history.requested_config`), refused with the protocol's errors."""
    if preset not in PRESETS:
        raise errors.UnknownPreset(
            f"unknown preset {preset!r}: this server has {', '.join(sorted(PRESETS))}"
        )
    try:
        recorded = _record_config(as_recorded) if as_recorded else None
        return settings_history.requested_config(preset, overrides, recorded, observations)
    except ConfigError as error:
        raise errors.BadConfig(str(error)) from None


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
