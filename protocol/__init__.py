"""The contract between overtake's parts: environment ids, wire messages, the codec, key
expressions and the Zenoh session settings. Imports nothing else of the project."""

from .codec import decode, encode, version_text
from .envs import HIGHWAY_ENV_ID, REMOTE_HIGHWAY_ENV_ID, register_environments
from .errors import (BadAction, BadConfig, ConnectError, DecodeError, NotOwner, ProtocolError,
                     ServerFull, ServerLost, StepTimeout, UnknownArena, UnknownPreset,
                     VersionMismatch, error_from_code)
from .messages import ACTION_COUNT, ACTION_NAMES, PROTOCOL_HISTORY, PROTOCOL_VERSION

__all__ = ["ACTION_COUNT", "ACTION_NAMES", "HIGHWAY_ENV_ID", "PROTOCOL_HISTORY",
           "PROTOCOL_VERSION", "REMOTE_HIGHWAY_ENV_ID", "BadAction", "BadConfig", "ConnectError",
           "DecodeError", "NotOwner", "ProtocolError", "ServerFull", "ServerLost", "StepTimeout",
           "UnknownArena", "UnknownPreset", "VersionMismatch", "decode", "encode",
           "error_from_code", "register_environments", "version_text"]
