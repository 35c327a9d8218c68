"""The contract between overtake's parts, and nothing else: the vocabulary, the version, the
wire messages and their records, the codec, the key expressions, the specs, the errors. Imports
nothing else of the project, and no Gymnasium, PettingZoo, Zenoh or ctypes: the environments
over this contract are overtake.envs, the mechanisms that carry it overtake.ipc.

Importing the package loads only the standard library and numpy: the codec (msgpack) loads
when it is first used, so the simulation core can read the vocabulary without pulling in the
wire.
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

# Names served on first use, and the module each comes from.
_LAZY = {
    "decode": "codec",
    "encode": "codec",
    "version_text": "codec",
}


def __getattr__(name: str) -> Any:
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    return getattr(importlib.import_module(f"{__name__}.{module}"), name)


__all__ = [
    "ACTION_COUNT",
    "ACTION_NAMES",
    "METRIC_FIELDS",
    "PROTOCOL_HISTORY",
    "PROTOCOL_VERSION",
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
    "version_text",
]
