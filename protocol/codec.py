"""The one codec: messages to msgpack bytes and back, validating everything on the way in.

A frame is the msgpack array ``[major, minor, type, body]``: the protocol version, the
message's type tag and a map of its fields. Arrays travel as ``{"dtype", "shape", "data"}``
with the raw little-endian bytes (never lists of numbers: ``tolist`` is a hundred times
slower). Decoding checks the version, the tag, every field's type, every array's dtype, shape
and byte size, and then the message's own rules; anything wrong raises
:class:`~overtake.protocol.errors.DecodeError` (or :class:`VersionMismatch`) saying what was
expected and what came. Random bytes never escape as another exception.
"""

from __future__ import annotations

import functools
import types
import typing
from dataclasses import fields, is_dataclass
from typing import Any, TypeVar

import msgpack
import numpy as np

from .errors import DecodeError, ProtocolError, VersionMismatch
from .messages import (MAX_ARRAY_DIMS, MAX_FRAME_BYTES, MAX_TEXT_CHARS, MESSAGE_TYPES,
                       PROTOCOL_VERSION, WIRE_DTYPES, Message, Part)

M = TypeVar("M", bound=Message)

_DTYPE_NAMES = {dtype: name for name, dtype in WIRE_DTYPES.items()}


def version_text(version: tuple[int, int] = PROTOCOL_VERSION) -> str:
    return f"{version[0]}.{version[1]}"


# --- encoding ---------------------------------------------------------------------------------

def _plain(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        dtype = value.dtype.newbyteorder("<") if value.dtype.byteorder == ">" else value.dtype
        name = _DTYPE_NAMES.get(dtype)
        if name is None:
            raise TypeError(f"arrays travel as one of {sorted(WIRE_DTYPES)}, got {value.dtype}")
        data = np.ascontiguousarray(value, dtype=WIRE_DTYPES[name])
        return {"dtype": name, "shape": list(data.shape), "data": data.tobytes()}
    if isinstance(value, Part):
        return {f.name: _plain(getattr(value, f.name)) for f in fields(value)}
    if isinstance(value, (tuple, list)):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, np.generic):  # msgpack refuses numpy scalars
        return value.item()
    return value


def encode(message: Message) -> bytes:
    """The frame of ``message``."""
    if not isinstance(message, Message):
        raise TypeError(f"expected an overtake message, got {type(message).__name__}")
    body = {f.name: _plain(getattr(message, f.name)) for f in fields(message)}
    return msgpack.packb([PROTOCOL_VERSION[0], PROTOCOL_VERSION[1], message.TYPE, body],
                         use_bin_type=True)


# --- decoding ---------------------------------------------------------------------------------

def _kind(value: Any) -> str:
    return type(value).__name__


def _array(value: Any, path: str) -> np.ndarray:
    if not isinstance(value, dict) or set(value) != {"dtype", "shape", "data"}:
        raise DecodeError(f"{path}: expected an array {{dtype, shape, data}}, got {_kind(value)}"
                          + (f" with keys {sorted(map(str, value))}" if isinstance(value, dict)
                             else ""))
    dtype_name, shape, data = value["dtype"], value["shape"], value["data"]
    if dtype_name not in WIRE_DTYPES:
        raise DecodeError(f"{path}: dtype must be one of {sorted(WIRE_DTYPES)}, got {dtype_name!r}")
    if (not isinstance(shape, list) or len(shape) > MAX_ARRAY_DIMS
            or not all(type(s) is int and 0 <= s <= MAX_FRAME_BYTES for s in shape)):
        raise DecodeError(f"{path}: shape must be a list of at most {MAX_ARRAY_DIMS} sizes, "
                          f"got {shape!r}")
    if not isinstance(data, bytes):
        raise DecodeError(f"{path}: data must be bytes, got {_kind(data)}")
    dtype = WIRE_DTYPES[dtype_name]
    count = 1
    for s in shape:
        count *= s
    if count * dtype.itemsize != len(data):
        raise DecodeError(f"{path}: {dtype_name} of shape {tuple(shape)} needs "
                          f"{count * dtype.itemsize} bytes, got {len(data)}")
    array = np.frombuffer(data, dtype=dtype).reshape(shape)
    if dtype_name == "bool" and count and data.translate(None, b"\x00\x01"):
        raise DecodeError(f"{path}: bool array holds bytes other than 0 and 1")
    # A writable native-order copy: callers may modify what they receive.
    return array.astype(dtype.newbyteorder("="), copy=True)


def _text(value: Any, path: str) -> str:
    if not isinstance(value, str):
        raise DecodeError(f"{path}: expected text, got {_kind(value)}")
    return value


def _convert(value: Any, hint: Any, path: str) -> Any:
    """``value`` from msgpack as the Python type ``hint`` (a field annotation)."""
    origin = typing.get_origin(hint)
    if origin in (types.UnionType, typing.Union):
        options = typing.get_args(hint)
        if value is None:
            if type(None) in options:
                return None
            raise DecodeError(f"{path}: expected a value, got nil")
        if all(o in (bool, int, float, str) for o in options):  # a plain scalar
            if type(value) in options or (type(value) is int and float in options):
                return value
            raise DecodeError(f"{path}: expected one of "
                              f"{', '.join(o.__name__ for o in options)}, got {_kind(value)}")
        rest = [o for o in options if o is not type(None)]
        if len(rest) == 1:
            return _convert(value, rest[0], path)
        raise TypeError(f"unsupported annotation {hint}")  # pragma: no cover - schema bug
    if hint is np.ndarray:
        return _array(value, path)
    if hint is str:
        return _text(value, path)
    if hint is bytes:
        if not isinstance(value, bytes):
            raise DecodeError(f"{path}: expected bytes, got {_kind(value)}")
        return value
    if hint is bool:
        if not isinstance(value, bool):
            raise DecodeError(f"{path}: expected true or false, got {_kind(value)}")
        return value
    if hint is int:
        if type(value) is not int:
            raise DecodeError(f"{path}: expected an integer, got {_kind(value)}")
        return value
    if hint is float:
        if type(value) not in (int, float):
            raise DecodeError(f"{path}: expected a number, got {_kind(value)}")
        return float(value)
    if origin is tuple:
        item = typing.get_args(hint)[0]
        if not isinstance(value, list):
            raise DecodeError(f"{path}: expected a list, got {_kind(value)}")
        return tuple(_convert(v, item, f"{path}[{i}]") for i, v in enumerate(value))
    if origin is dict:
        key_hint, item = typing.get_args(hint)
        if not isinstance(value, dict):
            raise DecodeError(f"{path}: expected a map, got {_kind(value)}")
        return {_text(k, f"{path} key"): _convert(v, item, f"{path}[{k!r}]")
                for k, v in value.items()}
    if isinstance(hint, type) and is_dataclass(hint):
        return _build(hint, value, path)
    raise TypeError(f"unsupported annotation {hint}")  # pragma: no cover - schema bug


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls)


def _build(cls: type, body: Any, path: str, peer_minor: int = PROTOCOL_VERSION[1]) -> Any:
    if not isinstance(body, dict):
        raise DecodeError(f"{path}: expected a map of {cls.__name__} fields, got {_kind(body)}")
    hints = _hints(cls)
    names = [f.name for f in fields(cls)]
    missing = [n for n in names if n not in body]
    if missing:
        raise DecodeError(f"{path}: {cls.__name__} lacks field(s) {missing}")
    unknown = sorted(map(str, set(body) - set(names)))
    if unknown and peer_minor <= PROTOCOL_VERSION[1]:
        # Only a newer minor version may add fields (which this side then ignores).
        raise DecodeError(f"{path}: {cls.__name__} has unknown field(s) {unknown}; "
                          f"expected {names}")
    values = {n: _convert(body[n], hints[n], f"{path}.{n}") for n in names}
    try:
        return cls(**values)
    except DecodeError as error:
        raise DecodeError(f"{path}: {error}") from None


def decode(data: bytes | bytearray | memoryview, expect: type[M] | tuple[type[Message], ...]
           | None = None) -> M:
    """The message in ``data``; with ``expect``, it must be one of those types.

    An :class:`ErrorReply` is always accepted (the caller decides what to raise).
    """
    from .messages import ErrorReply

    if len(data) > MAX_FRAME_BYTES:
        raise DecodeError(f"frame of {len(data)} bytes exceeds the limit of {MAX_FRAME_BYTES}")
    try:
        frame = msgpack.unpackb(bytes(data), raw=False, use_list=True, strict_map_key=True,
                                max_str_len=MAX_TEXT_CHARS, max_bin_len=MAX_FRAME_BYTES,
                                max_array_len=MAX_FRAME_BYTES, max_map_len=MAX_TEXT_CHARS,
                                max_ext_len=0)
    except Exception as error:  # msgpack raises many types on garbage; all mean the same
        raise DecodeError(f"not a msgpack frame ({type(error).__name__}: {error})") from None
    if not (isinstance(frame, list) and len(frame) == 4):
        raise DecodeError(f"expected a frame [major, minor, type, body], got {_kind(frame)}"
                          + (f" of length {len(frame)}" if isinstance(frame, list) else ""))
    major, minor, tag, body = frame
    if type(major) is not int or type(minor) is not int:
        raise DecodeError(f"expected integer protocol version numbers, got {major!r}.{minor!r}")
    if major != PROTOCOL_VERSION[0]:
        raise VersionMismatch(f"peer speaks overtake protocol {major}.{minor}, this side speaks "
                              f"{version_text()}; major versions must match (upgrade the older "
                              "side)")
    cls = MESSAGE_TYPES.get(tag) if isinstance(tag, str) else None
    if cls is None:
        raise DecodeError(f"unknown message type {tag!r}; expected one of "
                          f"{sorted(MESSAGE_TYPES)}")
    if expect is not None:
        wanted = expect if isinstance(expect, tuple) else (expect,)
        if cls not in wanted and cls is not ErrorReply:
            raise DecodeError(f"expected {' or '.join(w.TYPE for w in wanted)}, got {tag}")
    try:
        return _build(cls, body, tag, peer_minor=minor)
    except ProtocolError:
        raise
    except (ValueError, TypeError, OverflowError) as error:  # e.g. an absurd reshape
        raise DecodeError(f"{tag}: {error}") from None
