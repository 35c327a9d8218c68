"""The one codec: messages to msgpack bytes and back, validating everything on the way in.

A frame is the msgpack array ``[major, minor, type, body]``: the protocol version, the
message's type tag and a map of its fields. Arrays travel as ``{"dtype", "shape", "data"}``
with the raw little-endian bytes (never lists of numbers: ``tolist`` is a hundred times
slower). Decoding checks the version, the tag, every field's type, every array's dtype, shape
and byte size, and then the message's own rules; anything wrong raises
:class:`~overtake.protocol.errors.DecodeError` (or :class:`VersionMismatch`) saying what was
expected and what came. A field typed as the family of channel offers
(:class:`~overtake.protocol.channel_offers.ChannelOffer`) travels as ``[transport, fields]``.
Random bytes never escape as another exception.
"""

from __future__ import annotations

import functools
import types
import typing
from collections.abc import Callable
from dataclasses import MISSING, fields, is_dataclass
from typing import Any, TypeVar, overload

import msgpack
import numpy as np

from .channel_offers import ChannelOffer, offer_type
from .errors import DecodeError, ProtocolError, VersionMismatch
from .messages import (
    MAX_ARRAY_DIMS,
    MAX_FRAME_BYTES,
    MAX_TEXT_CHARS,
    MESSAGE_TYPES,
    PROTOCOL_VERSION,
    WIRE_DTYPES,
    ErrorReply,
    Message,
)

M = TypeVar("M", bound=Message)

_DTYPE_NAMES = {dtype: name for name, dtype in WIRE_DTYPES.items()}


def version_text(version: tuple[int, int] = PROTOCOL_VERSION) -> str:
    return f"{version[0]}.{version[1]}"


# --- encoding ---------------------------------------------------------------------------------

# Encoding is compiled once per field annotation too: an encoder turns a field's value into
# what msgpack packs (arrays into {dtype, shape, data}, numpy scalars into Python ones).
Encoder = Callable[[Any], Any]


def _array_out(value: Any) -> dict[str, Any]:
    if not isinstance(value, np.ndarray):
        raise TypeError(f"expected a numpy array, got {type(value).__name__}")
    if value.ndim > MAX_ARRAY_DIMS:
        raise ValueError(
            f"arrays travel with at most {MAX_ARRAY_DIMS} dimensions, got {value.ndim}"
        )
    dtype = value.dtype.newbyteorder("<") if value.dtype.byteorder == ">" else value.dtype
    name = _DTYPE_NAMES.get(dtype)
    if name is None:
        raise TypeError(f"arrays travel as one of {sorted(WIRE_DTYPES)}, got {value.dtype}")
    data = np.ascontiguousarray(value, dtype=WIRE_DTYPES[name])
    return {"dtype": name, "shape": list(data.shape), "data": data.tobytes()}


def _text_out(value: Any) -> Any:
    if isinstance(value, str) and len(value) > MAX_TEXT_CHARS:
        raise ValueError(f"text of {len(value)} characters exceeds the limit of {MAX_TEXT_CHARS}")
    return value


def _scalar_out(value: Any) -> Any:
    if isinstance(value, np.generic):  # msgpack refuses numpy scalars
        return value.item()
    return _text_out(value)


@functools.cache
def _encoder(hint: Any) -> Encoder:
    """The encoder of values of the Python type ``hint`` (a field annotation)."""
    if hint is np.ndarray:
        return _array_out
    if hint in (str, bytes, bool, int, float):
        return _scalar_out
    origin = typing.get_origin(hint)
    if origin in (types.UnionType, typing.Union):
        rest = tuple(o for o in typing.get_args(hint) if o is not type(None))
        if len(rest) == 1:
            inner = _encoder(rest[0])
            return lambda value: None if value is None else inner(value)
        return _scalar_out  # a union of scalars (the schema has no other unions)
    if origin is tuple:
        item = _encoder(typing.get_args(hint)[0])
        return lambda value: [item(v) for v in value]
    if origin is dict:
        item = _encoder(typing.get_args(hint)[1])
        return lambda value: {k: item(v) for k, v in value.items()}
    if hint is ChannelOffer:
        return _tagged_out
    if isinstance(hint, type) and is_dataclass(hint):
        return _record_encoder(hint)
    raise TypeError(f"unsupported annotation {hint}")  # pragma: no cover - schema bug


def _tagged_out(value: Any) -> list[Any]:
    """A channel offer of any transport: ``[its transport, its fields]``."""
    if not isinstance(value, ChannelOffer) or type(value) is ChannelOffer:
        raise TypeError(f"expected a transport's ChannelOffer, got {type(value).__name__}")
    return [value.TRANSPORT, _record_encoder(type(value))(value)]  # type: ignore[arg-type]


@functools.cache
def _record_encoder(cls: type) -> Encoder:
    hints = typing.get_type_hints(cls)
    spec = tuple((f.name, _encoder(hints[f.name])) for f in fields(cls))

    def record(value: Any) -> dict[str, Any]:
        if not isinstance(value, cls):
            raise TypeError(f"expected {cls.__name__}, got {type(value).__name__}")
        return {name: encode_field(getattr(value, name)) for name, encode_field in spec}

    return record


def encode(message: Message) -> bytes:
    """The frame of ``message``."""
    if not isinstance(message, Message):
        raise TypeError(f"expected an overtake message, got {type(message).__name__}")
    # Classes are hashable; mypy reads Part's `__hash__ = None` (for instances) as theirs.
    body = _record_encoder(type(message))(message)  # type: ignore[arg-type]
    return msgpack.packb(
        [PROTOCOL_VERSION[0], PROTOCOL_VERSION[1], message.TYPE, body], use_bin_type=True
    )


# --- decoding ---------------------------------------------------------------------------------


def _kind(value: Any) -> str:
    return type(value).__name__


# Decoding is compiled once per field annotation into a converter ``(value, peer_minor)``;
# converters raise DecodeError with a message relative to their field, and each record
# prefixes its field's name on the way out, so paths cost nothing unless something is wrong.
Converter = Callable[[Any, int], Any]


def _at(segment: str, error: DecodeError) -> DecodeError:
    """``error`` one level up: ``.name``/``[i]`` segments join into one path."""
    text = str(error)
    return DecodeError(f"{segment}{text}" if text[:1] in ".[" else f"{segment}: {text}")


_ARRAY_KEYS = frozenset(("dtype", "shape", "data"))


def _array(value: Any, _minor: int) -> np.ndarray:
    if type(value) is not dict or len(value) != 3 or not _ARRAY_KEYS.issuperset(value):
        raise DecodeError(
            f"expected an array {{dtype, shape, data}}, got {_kind(value)}"
            + (f" with keys {sorted(map(str, value))}" if isinstance(value, dict) else "")
        )
    dtype_name, shape, data = value["dtype"], value["shape"], value["data"]
    dtype = WIRE_DTYPES.get(dtype_name) if type(dtype_name) is str else None
    if dtype is None:
        raise DecodeError(f"dtype must be one of {sorted(WIRE_DTYPES)}, got {dtype_name!r}")
    count = 1
    if type(shape) is list and len(shape) <= MAX_ARRAY_DIMS:
        for s in shape:
            if type(s) is not int or not 0 <= s <= MAX_FRAME_BYTES:
                count = -1
                break
            count *= s
    else:
        count = -1
    if count < 0:
        raise DecodeError(f"shape must be a list of at most {MAX_ARRAY_DIMS} sizes, got {shape!r}")
    if type(data) is not bytes:
        raise DecodeError(f"data must be bytes, got {_kind(data)}")
    if count * dtype.itemsize != len(data):
        raise DecodeError(
            f"{dtype_name} of shape {tuple(shape)} needs "
            f"{count * dtype.itemsize} bytes, got {len(data)}"
        )
    if dtype_name == "bool" and count and data.translate(None, b"\x00\x01"):
        raise DecodeError("bool array holds bytes other than 0 and 1")
    array = np.frombuffer(data, dtype=dtype).reshape(shape)
    # A writable native-order copy: callers may modify what they receive.
    return array.copy() if dtype.isnative else array.astype(dtype.newbyteorder("="))


def _text(value: Any, _minor: int) -> str:
    if type(value) is not str:
        raise DecodeError(f"expected text, got {_kind(value)}")
    if len(value) > MAX_TEXT_CHARS:
        raise DecodeError(f"text of {len(value)} characters exceeds the limit of {MAX_TEXT_CHARS}")
    return value


def _bytes(value: Any, _minor: int) -> bytes:
    if type(value) is not bytes:
        raise DecodeError(f"expected bytes, got {_kind(value)}")
    return value


def _bool(value: Any, _minor: int) -> bool:
    if type(value) is not bool:
        raise DecodeError(f"expected true or false, got {_kind(value)}")
    return value


def _int(value: Any, _minor: int) -> int:
    if type(value) is not int:
        raise DecodeError(f"expected an integer, got {_kind(value)}")
    return value


def _float(value: Any, _minor: int) -> float:
    if type(value) is not int and type(value) is not float:
        raise DecodeError(f"expected a number, got {_kind(value)}")
    return float(value)


_SIMPLE: dict[Any, Converter] = {
    np.ndarray: _array,
    str: _text,
    bytes: _bytes,
    bool: _bool,
    int: _int,
    float: _float,
}


@functools.cache
def _converter(hint: Any) -> Converter:
    """The converter of msgpack values into the Python type ``hint`` (a field annotation)."""
    simple = _SIMPLE.get(hint)
    if simple is not None:
        return simple
    origin = typing.get_origin(hint)
    if origin in (types.UnionType, typing.Union):
        options = typing.get_args(hint)
        nullable = type(None) in options
        rest = tuple(o for o in options if o is not type(None))
        if all(o in (bool, int, float, str) for o in rest) and len(rest) > 1:
            names = ", ".join(o.__name__ for o in rest)

            def scalar(value: Any, minor: int) -> Any:
                if value is None and nullable:
                    return None
                if type(value) in rest or (type(value) is int and float in rest):
                    return _text(value, minor) if type(value) is str else value
                raise DecodeError(f"expected one of {names}, got {_kind(value)}")

            return scalar
        if len(rest) == 1:
            inner = _converter(rest[0])

            def optional(value: Any, minor: int) -> Any:
                if value is None:
                    if nullable:
                        return None
                    raise DecodeError("expected a value, got nil")
                return inner(value, minor)

            return optional
    if origin is tuple:
        item = _converter(typing.get_args(hint)[0])

        def sequence(value: Any, minor: int) -> tuple:
            if type(value) is not list:
                raise DecodeError(f"expected a list, got {_kind(value)}")
            out = []
            for i, v in enumerate(value):
                try:
                    out.append(item(v, minor))
                except DecodeError as error:
                    raise _at(f"[{i}]", error) from None
            return tuple(out)

        return sequence
    if origin is dict:
        item = _converter(typing.get_args(hint)[1])

        def mapping(value: Any, minor: int) -> dict:
            if type(value) is not dict:
                raise DecodeError(f"expected a map, got {_kind(value)}")
            out = {}
            for k, v in value.items():
                try:
                    out[_text(k, minor)] = item(v, minor)
                except DecodeError as error:
                    raise _at(f"[{k!r}]", error) from None
            return out

        return mapping
    if hint is ChannelOffer:
        return _tagged
    if isinstance(hint, type) and is_dataclass(hint):
        return functools.partial(_build, hint)
    raise TypeError(f"unsupported annotation {hint}")  # pragma: no cover - schema bug


def _tagged(value: Any, minor: int) -> ChannelOffer:
    """A channel offer from ``[transport, fields]``, built as that transport's offer type."""
    if type(value) is not list or len(value) != 2:
        raise DecodeError(f"expected a [transport, offer] pair, got {_kind(value)}")
    tag, body = value
    if type(tag) is not str:
        raise DecodeError(f"expected a transport's name, got {_kind(tag)}")
    offer: ChannelOffer = _build(offer_type(tag), body, minor)
    return offer


@functools.cache
def _fields(cls: type) -> tuple[tuple[str, Converter], ...]:
    hints = typing.get_type_hints(cls)
    return tuple((f.name, _converter(hints[f.name])) for f in fields(cls))


@functools.cache
def _added(cls: type) -> dict[str, tuple[int, Any]]:
    """Fields a later minor version added (``metadata={"since": minor}``): name -> (that minor,
    the value a record from an older peer gets)."""
    out: dict[str, tuple[int, Any]] = {}
    for f in fields(cls):
        since = f.metadata.get("since")
        if since is None:
            continue
        if f.default is MISSING:  # pragma: no cover - a schema bug, caught by the tests
            raise TypeError(f"{cls.__name__}.{f.name} is marked since {since} without a default")
        out[f.name] = (since, f.default)
    return out


@functools.cache
def _older_defaults(cls: type, peer_minor: int) -> dict[str, Any]:
    """What a peer of ``peer_minor`` does not send, because it predates those fields."""
    return {name: default for name, (since, default) in _added(cls).items() if peer_minor < since}


def _build(cls: type, body: Any, peer_minor: int) -> Any:
    """A record of ``cls`` from its msgpack map; a newer minor version may add fields, and an
    older one lacks those this side added since (they take their defaults)."""
    if type(body) is not dict:
        raise DecodeError(f"expected a map of {cls.__name__} fields, got {_kind(body)}")
    spec = _fields(cls)
    older = _older_defaults(cls, peer_minor) if peer_minor < PROTOCOL_VERSION[1] else {}
    if len(body) != len(spec) or peer_minor != PROTOCOL_VERSION[1]:
        names = [name for name, _ in spec]
        missing = [n for n in names if n not in body and n not in older]
        if missing:
            raise DecodeError(f"{cls.__name__} lacks field(s) {missing}")
        unknown = sorted(map(str, set(body) - set(names)))
        if unknown and peer_minor <= PROTOCOL_VERSION[1]:
            # Only a newer minor version may add fields (which this side then ignores).
            raise DecodeError(f"{cls.__name__} has unknown field(s) {unknown}; expected {names}")
    values = {}
    for name, convert in spec:
        if name not in body:
            if name in older:
                values[name] = older[name]
                continue
            raise DecodeError(f"{cls.__name__} lacks field {name!r}")
        try:
            values[name] = convert(body[name], peer_minor)
        except DecodeError as error:
            raise _at(f".{name}", error) from None
    return cls(**values)


@overload
def decode(data: bytes | bytearray | memoryview, expect: type[M]) -> M | ErrorReply: ...


@overload
def decode(
    data: bytes | bytearray | memoryview, expect: tuple[type[Message], ...] | None = None
) -> Message: ...


def decode(
    data: bytes | bytearray | memoryview,
    expect: type[Message] | tuple[type[Message], ...] | None = None,
) -> Message:
    """The message in ``data``; with ``expect``, it must be one of those types or an
    :class:`ErrorReply`, which is always accepted (the caller decides what to raise): a
    decode that expects ``Steps`` returns ``Steps | ErrorReply``.
    """
    if len(data) > MAX_FRAME_BYTES:
        raise DecodeError(f"frame of {len(data)} bytes exceeds the limit of {MAX_FRAME_BYTES}")
    try:
        frame = msgpack.unpackb(
            bytes(data),
            raw=False,
            use_list=True,
            strict_map_key=True,
            max_str_len=4 * MAX_TEXT_CHARS,
            max_bin_len=MAX_FRAME_BYTES,
            max_array_len=MAX_FRAME_BYTES,
            max_map_len=MAX_TEXT_CHARS,
            max_ext_len=0,
        )
    except Exception as error:  # msgpack raises many types on garbage; all mean the same
        raise DecodeError(f"not a msgpack frame ({type(error).__name__}: {error})") from None
    if not (isinstance(frame, list) and len(frame) == 4):
        raise DecodeError(
            f"expected a frame [major, minor, type, body], got {_kind(frame)}"
            + (f" of length {len(frame)}" if isinstance(frame, list) else "")
        )
    major, minor, tag, body = frame
    if type(major) is not int or type(minor) is not int or major < 0 or minor < 0:
        raise DecodeError(
            f"expected non-negative integer protocol version numbers, got {major!r}.{minor!r}"
        )
    if major != PROTOCOL_VERSION[0]:
        raise VersionMismatch(
            f"peer speaks overtake protocol {major}.{minor}, this side speaks "
            f"{version_text()}; major versions must match (upgrade the older "
            "side)"
        )
    cls = MESSAGE_TYPES.get(tag) if isinstance(tag, str) else None
    if cls is None:
        raise DecodeError(f"unknown message type {tag!r}; expected one of {sorted(MESSAGE_TYPES)}")
    if expect is not None:
        wanted = expect if isinstance(expect, tuple) else (expect,)
        if cls not in wanted and cls is not ErrorReply:
            raise DecodeError(f"expected {' or '.join(w.TYPE for w in wanted)}, got {tag}")
    try:
        return _build(cls, body, minor)
    except ProtocolError as error:
        if isinstance(error, DecodeError):
            raise _at(tag, error) from None
        raise
    except (ValueError, TypeError, OverflowError) as error:  # e.g. an absurd reshape
        raise DecodeError(f"{tag}: {error}") from None
