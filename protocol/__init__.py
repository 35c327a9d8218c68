"""The contract between overtake's parts: vocabulary, wire messages, the codec, key expressions,
errors, environment ids and the Zenoh session settings. Imports nothing else of the project.

Importing the package loads only the standard library and numpy: the codec (msgpack), the
Gymnasium helpers (:mod:`.envs`) and the Zenoh transport (:mod:`.transport`) load when they are
first used, so the simulation core can read the vocabulary without pulling in the wire.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from .errors import (
    BadAction,
    BadConfig,
    ConnectError,
    DecodeError,
    NotOwner,
    ProtocolError,
    ServerBusy,
    ServerFull,
    ServerLost,
    StepTimeout,
    UnknownArena,
    UnknownPreset,
    VersionMismatch,
    error_from_code,
)
from .messages import PROTOCOL_HISTORY, PROTOCOL_VERSION
from .vocabulary import ACTION_COUNT, ACTION_NAMES, METRIC_FIELDS

if TYPE_CHECKING:
    from .codec import decode, encode, version_text
    from .envs import HIGHWAY_ENV_ID, REMOTE_HIGHWAY_ENV_ID, register_environments

# Names served on first use, and the module each comes from.
_LAZY = {
    "decode": "codec",
    "encode": "codec",
    "version_text": "codec",
    "HIGHWAY_ENV_ID": "envs",
    "REMOTE_HIGHWAY_ENV_ID": "envs",
    "register_environments": "envs",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{module}"), name)


__all__ = [
    "ACTION_COUNT",
    "ACTION_NAMES",
    "HIGHWAY_ENV_ID",
    "METRIC_FIELDS",
    "PROTOCOL_HISTORY",
    "PROTOCOL_VERSION",
    "REMOTE_HIGHWAY_ENV_ID",
    "BadAction",
    "BadConfig",
    "ConnectError",
    "DecodeError",
    "NotOwner",
    "ProtocolError",
    "ServerBusy",
    "ServerFull",
    "ServerLost",
    "StepTimeout",
    "UnknownArena",
    "UnknownPreset",
    "VersionMismatch",
    "decode",
    "encode",
    "error_from_code",
    "register_environments",
    "version_text",
]
