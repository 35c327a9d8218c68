"""The one codec: messages to msgpack bytes and back, validating everything on the way in.

A frame is the msgpack array ``[major, minor, type, body]``: the protocol version, the
message's type tag and a map of its fields. Arrays travel as ``{"dtype", "shape", "data"}``
with the raw little-endian bytes (never lists of numbers: ``tolist`` is a hundred times
slower). Since 1.2 a message's per-agent arrays (``ROWS``, the Steps of every round) may
instead travel row-packed: one ``rows`` entry ``{"count", "layout", "data"}`` holds them all
in one byte block, described by a layout text checked once and then kept, so decoding a
round costs a size check and a view per array. Decoding checks the version, the tag, every field's type, every array's dtype, shape
and byte size, and then the message's own rules; anything wrong raises
:class:`~overtake.protocol.errors.DecodeError` (or :class:`VersionMismatch`) saying what was
expected and what came. Random bytes never escape as another exception.
"""

from __future__ import annotations

import functools
import types
import typing
from collections.abc import Callable
from dataclasses import MISSING, dataclass, fields, is_dataclass
from typing import Any, TypeVar

import msgpack
import numpy as np

from .errors import DecodeError, ProtocolError, VersionMismatch
from .messages import (MAX_ARRAY_DIMS, MAX_FRAME_BYTES, MAX_TEXT_CHARS, MESSAGE_TYPES,
                       NAME_PATTERN, PROTOCOL_VERSION, ROWS_SINCE_MINOR, WIRE_DTYPES, Message)

M = TypeVar("M", bound=Message)

_DTYPE_NAMES = {dtype: name for name, dtype in WIRE_DTYPES.items()}


def version_text(version: tuple[int, int] = PROTOCOL_VERSION) -> str:
    return f"{version[0]}.{version[1]}"


# --- encoding ---------------------------------------------------------------------------------

# Encoding is compiled once per field annotation too: an encoder turns a field's value into
# what msgpack packs (arrays into {dtype, shape, data}, numpy scalars into Python ones).
Encoder = Callable[[Any], Any]


def _wire_array(value: Any) -> tuple[str, np.ndarray]:
    """``value``'s wire dtype name, and its values contiguous in that (little-endian) dtype."""
    if not isinstance(value, np.ndarray):
        raise TypeError(f"expected a numpy array, got {type(value).__name__}")
    if value.ndim > MAX_ARRAY_DIMS:
        raise ValueError(f"arrays travel with at most {MAX_ARRAY_DIMS} dimensions, got "
                         f"{value.ndim}")
    dtype = value.dtype.newbyteorder("<") if value.dtype.byteorder == ">" else value.dtype
    name = _DTYPE_NAMES.get(dtype)
    if name is None:
        raise TypeError(f"arrays travel as one of {sorted(WIRE_DTYPES)}, got {value.dtype}")
    return name, np.ascontiguousarray(value, dtype=WIRE_DTYPES[name])


def _array_out(value: Any) -> dict[str, Any]:
    name, data = _wire_array(value)
    return {"dtype": name, "shape": list(data.shape), "data": data.tobytes()}


def _text_out(value: Any) -> Any:
    if isinstance(value, str) and len(value) > MAX_TEXT_CHARS:
        raise ValueError(f"text of {len(value)} characters exceeds the limit of "
                         f"{MAX_TEXT_CHARS}")
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
    if isinstance(hint, type) and is_dataclass(hint):
        return _record_encoder(hint)
    raise TypeError(f"unsupported annotation {hint}")  # pragma: no cover - schema bug


@functools.cache
def _record_encoder(cls: type) -> Encoder:
    hints = typing.get_type_hints(cls)
    spec = tuple((f.name, _encoder(hints[f.name])) for f in fields(cls))

    def record(value: Any) -> dict[str, Any]:
        if not isinstance(value, cls):
            raise TypeError(f"expected {cls.__name__}, got {type(value).__name__}")
        return {name: encode_field(getattr(value, name)) for name, encode_field in spec}
    return record


def encode(message: Message, minor: int = PROTOCOL_VERSION[1]) -> bytes:
    """The frame of ``message``, in the form a peer of protocol ``minor`` (this major) reads:
    row-packed from 1.2 on where the message has ``ROWS``, field by field before."""
    if not isinstance(message, Message):
        raise TypeError(f"expected an overtake message, got {type(message).__name__}")
    cls = type(message)
    if cls.ROWS and minor >= ROWS_SINCE_MINOR:
        body = _packed_record_encoder(cls)(message)
    else:
        body = _record_encoder(cls)(message)
    return msgpack.packb([PROTOCOL_VERSION[0], PROTOCOL_VERSION[1], message.TYPE, body],
                         use_bin_type=True)


# --- row-packed records (protocol 1.2) --------------------------------------------------------

# The ``rows`` entry of a row-packed body: ``count`` agents, and each ROWS array's ``count``
# rows one after another in ``data``, each array starting at a multiple of ROW_ALIGN bytes
# (so float64 views are aligned). ``layout`` names them in order, one ``name:dtype:shape``
# entry each, joined by ";": the name is the field, or ``field.key`` for a map's array; the
# shape is the row's, sizes joined by "x" (empty for one value a row), e.g.
# ``reward:float64:;observations.camera:uint8:84x84``.
ROWS_KEY = "rows"
ROW_ALIGN = 8
MAX_LAYOUT_CHARS = 8192
MAX_LAYOUT_ENTRIES = 64
# Layouts parsed and checked once are kept (a peer sends the same one every round); a peer
# inventing new ones gets them checked each time once this many are kept, nothing worse.
MAX_KEPT_LAYOUTS = 256


@functools.cache
def _row_maps(cls: type) -> dict[str, bool]:
    """``cls``'s ROWS fields, each mapped to whether it is a map of arrays (else an array)."""
    hints = typing.get_type_hints(cls)
    return {name: typing.get_origin(hints[name]) is dict for name in cls.ROWS}


_ROW_SHAPE_TEXT: dict[tuple[int, ...], str] = {}


@functools.cache
def _packed_record_encoder(cls: type) -> Encoder:
    rows = _row_maps(cls)
    others = tuple((name, encode_field) for name, encode_field in
                   ((f.name, _encoder(typing.get_type_hints(cls)[f.name])) for f in fields(cls))
                   if name not in rows)

    def record(value: Any) -> dict[str, Any]:
        if not isinstance(value, cls):
            raise TypeError(f"expected {cls.__name__}, got {type(value).__name__}")
        body = {name: encode_field(getattr(value, name)) for name, encode_field in others}
        entries: list[str] = []
        parts: list[bytes] = []
        count: int | None = None
        for name, is_map in rows.items():
            field_value = getattr(value, name)
            for key, array in (field_value.items() if is_map else ((None, field_value),)):
                # The common case (a native little-endian array of a wire dtype) is looked
                # up; anything else goes through the checks and conversion of _wire_array.
                dtype_name = _DTYPE_NAMES.get(array.dtype) if type(array) is np.ndarray \
                    else None
                if dtype_name is None or not 1 <= array.ndim <= MAX_ARRAY_DIMS:
                    dtype_name, array = _wire_array(array)
                label = name if key is None else f"{name}.{key}"
                shape = array.shape
                if not shape or (count is not None and shape[0] != count):
                    raise ValueError(f"{label} must have {count} rows (one per agent), got "
                                     f"shape {shape}")
                count = shape[0]
                row_shape = _ROW_SHAPE_TEXT.get(shape[1:])
                if row_shape is None:
                    row_shape = "x".join(map(str, shape[1:]))
                    if len(_ROW_SHAPE_TEXT) < MAX_KEPT_LAYOUTS:
                        _ROW_SHAPE_TEXT[shape[1:]] = row_shape
                entries.append(f"{label}:{dtype_name}:{row_shape}")
                raw = array.tobytes()  # C order, whatever the array's strides
                parts.append(raw)
                if len(raw) % ROW_ALIGN:
                    parts.append(bytes(ROW_ALIGN - len(raw) % ROW_ALIGN))
        if count is None:  # pragma: no cover - every ROWS schema has a plain array
            raise ValueError(f"{cls.__name__} has no per-agent array to count the rows by")
        body[ROWS_KEY] = {"count": count, "layout": ";".join(entries), "data": b"".join(parts)}
        return body
    return record


@dataclass(frozen=True)
class _RowArray:
    """One array of a checked layout."""

    field: str
    key: str | None
    dtype: np.dtype
    is_bool: bool
    native: bool
    shape: tuple[int, ...]   # of one row
    items: int               # values in one row
    row_bytes: int


_kept_layouts: dict[tuple[type, str], tuple[_RowArray, ...]] = {}


def _layout(cls: type, text: Any) -> tuple[_RowArray, ...]:
    """The arrays ``text`` lays out for ``cls``, checked (once per distinct text)."""
    kept = _kept_layouts.get((cls, text)) if type(text) is str else None
    if kept is not None:
        return kept
    if type(text) is not str:
        raise DecodeError(f"layout must be text, got {_kind(text)}")
    if len(text) > MAX_LAYOUT_CHARS:
        raise DecodeError(f"layout of {len(text)} characters exceeds the limit of "
                          f"{MAX_LAYOUT_CHARS}")
    maps = _row_maps(cls)
    entries = text.split(";") if text else []
    if len(entries) > MAX_LAYOUT_ENTRIES:
        raise DecodeError(f"layout of {len(entries)} arrays exceeds the limit of "
                          f"{MAX_LAYOUT_ENTRIES}")
    arrays: list[_RowArray] = []
    seen: set[str] = set()
    for entry in entries:
        parts = entry.split(":")
        if len(parts) != 3:
            raise DecodeError(f"layout entry {entry!r} is not name:dtype:shape")
        label, dtype_name, shape_text = parts
        name, dot, key = label.partition(".")
        if name not in maps:
            raise DecodeError(f"layout entry {entry!r} names no per-agent field of "
                              f"{cls.__name__}; expected one of {list(maps)}")
        if maps[name] != bool(dot):
            raise DecodeError(f"layout entry {entry!r}: {name} is "
                              + ("a map: expected field.key" if maps[name] else
                                 "an array: expected no .key"))
        if dot and not NAME_PATTERN.fullmatch(key):
            raise DecodeError(f"layout entry {entry!r}: the key must be 1-64 letters, digits, "
                              "'_', '.' or '-'")
        if label in seen:
            raise DecodeError(f"layout names {label} twice")
        seen.add(label)
        dtype = WIRE_DTYPES.get(dtype_name)
        if dtype is None:
            raise DecodeError(f"layout entry {entry!r}: dtype must be one of "
                              f"{sorted(WIRE_DTYPES)}")
        sizes = shape_text.split("x") if shape_text else []
        if len(sizes) > MAX_ARRAY_DIMS - 1 or not all(
                size.isascii() and size.isdigit() and len(size) <= 9 for size in sizes):
            raise DecodeError(f"layout entry {entry!r}: the row shape must be at most "
                              f"{MAX_ARRAY_DIMS - 1} sizes joined by 'x'")
        shape = tuple(int(size) for size in sizes)
        items = 1
        for size in shape:
            items *= size
        if items * dtype.itemsize > MAX_FRAME_BYTES:
            raise DecodeError(f"layout entry {entry!r}: a row of {items} values exceeds the "
                              "frame limit")
        arrays.append(_RowArray(field=name, key=key if dot else None, dtype=dtype,
                                is_bool=dtype_name == "bool", native=dtype.isnative,
                                shape=shape, items=items,
                                row_bytes=items * dtype.itemsize))
    missing = [name for name, is_map in maps.items() if not is_map and name not in seen]
    if missing:
        raise DecodeError(f"layout lacks {missing}")
    layout = tuple(arrays)
    if len(_kept_layouts) < MAX_KEPT_LAYOUTS:
        _kept_layouts[(cls, text)] = layout
    return layout


_ROWS_KEYS = frozenset(("count", "layout", "data"))


def _rows(cls: type, block: Any) -> dict[str, Any]:
    """The ROWS fields' values from a ``rows`` entry."""
    if type(block) is not dict or len(block) != 3 or not _ROWS_KEYS.issuperset(block):
        raise DecodeError("expected {count, layout, data}, got "
                          + (f"keys {sorted(map(str, block))}" if isinstance(block, dict)
                             else _kind(block)))
    count, data = block["count"], block["data"]
    if type(count) is not int or not 0 <= count <= MAX_FRAME_BYTES:
        raise DecodeError(f"count must be an integer from 0 to {MAX_FRAME_BYTES}, got "
                          f"{count!r}")
    if type(data) is not bytes:
        raise DecodeError(f"data must be bytes, got {_kind(data)}")
    layout = _layout(cls, block["layout"])
    needed = 0
    for array in layout:
        needed += -(-count * array.row_bytes // ROW_ALIGN) * ROW_ALIGN
    if needed != len(data):
        raise DecodeError(f"{count} row(s) of this layout need {needed} bytes, got {len(data)}")
    # One writable copy for all the arrays: callers may modify what they receive.
    buffer = bytearray(data)
    values: dict[str, Any] = {name: {} for name, is_map in _row_maps(cls).items() if is_map}
    offset = 0
    for array in layout:
        size = count * array.row_bytes
        if array.is_bool and size and buffer[offset:offset + size].translate(None, b"\x00\x01"):
            label = array.field if array.key is None else f"{array.field}.{array.key}"
            raise DecodeError(f"{label}: bool array holds bytes other than 0 and 1")
        if count:
            value = np.frombuffer(buffer, array.dtype, count * array.items, offset)
            value = value.reshape((count, *array.shape))
        else:
            value = np.empty((0, *array.shape), array.dtype)
        if not array.native:
            value = value.astype(array.dtype.newbyteorder("="))
        if array.key is None:
            values[array.field] = value
        else:
            values[array.field][array.key] = value
        offset += -(-size // ROW_ALIGN) * ROW_ALIGN
    return values


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
        raise DecodeError(f"expected an array {{dtype, shape, data}}, got {_kind(value)}"
                          + (f" with keys {sorted(map(str, value))}" if isinstance(value, dict)
                             else ""))
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
        raise DecodeError(f"shape must be a list of at most {MAX_ARRAY_DIMS} sizes, "
                          f"got {shape!r}")
    if type(data) is not bytes:
        raise DecodeError(f"data must be bytes, got {_kind(data)}")
    if count * dtype.itemsize != len(data):
        raise DecodeError(f"{dtype_name} of shape {tuple(shape)} needs "
                          f"{count * dtype.itemsize} bytes, got {len(data)}")
    if dtype_name == "bool" and count and data.translate(None, b"\x00\x01"):
        raise DecodeError("bool array holds bytes other than 0 and 1")
    array = np.frombuffer(data, dtype=dtype).reshape(shape)
    # A writable native-order copy: callers may modify what they receive.
    return array.copy() if dtype.isnative else array.astype(dtype.newbyteorder("="))


def _text(value: Any, _minor: int) -> str:
    if type(value) is not str:
        raise DecodeError(f"expected text, got {_kind(value)}")
    if len(value) > MAX_TEXT_CHARS:
        raise DecodeError(f"text of {len(value)} characters exceeds the limit of "
                          f"{MAX_TEXT_CHARS}")
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


_SIMPLE: dict[Any, Converter] = {np.ndarray: _array, str: _text, bytes: _bytes, bool: _bool,
                                 int: _int, float: _float}


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
    if isinstance(hint, type) and is_dataclass(hint):
        return functools.partial(_build, hint)
    raise TypeError(f"unsupported annotation {hint}")  # pragma: no cover - schema bug


@functools.cache
def _fields(cls: type) -> tuple[tuple[str, Converter], ...]:
    hints = typing.get_type_hints(cls)
    return tuple((f.name, _converter(hints[f.name])) for f in fields(cls))


@functools.cache
def _packed_fields(cls: type) -> tuple[tuple[str, Converter], ...]:
    """What a row-packed body of ``cls`` holds: its other fields, then ``rows``."""
    rows = _row_maps(cls)

    def convert_rows(value: Any, _minor: int) -> dict[str, Any]:
        return _rows(cls, value)
    return (*((name, convert) for name, convert in _fields(cls) if name not in rows),
            (ROWS_KEY, convert_rows))


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
    return {name: default for name, (since, default) in _added(cls).items()
            if peer_minor < since}


def _build(cls: type, body: Any, peer_minor: int) -> Any:
    """A record of ``cls`` from its msgpack map; a newer minor version may add fields, and an
    older one lacks those this side added since (they take their defaults)."""
    if type(body) is not dict:
        raise DecodeError(f"expected a map of {cls.__name__} fields, got {_kind(body)}")
    packed = bool(cls.ROWS) and ROWS_KEY in body
    spec = _packed_fields(cls) if packed else _fields(cls)
    older = _older_defaults(cls, peer_minor) if peer_minor < PROTOCOL_VERSION[1] else {}
    if len(body) != len(spec) or peer_minor != PROTOCOL_VERSION[1]:
        names = [name for name, _ in spec]
        missing = [n for n in names if n not in body and n not in older]
        if missing:
            raise DecodeError(f"{cls.__name__} lacks field(s) {missing}")
        unknown = sorted(map(str, set(body) - set(names)))
        if packed and set(unknown) & set(cls.ROWS):
            raise DecodeError(f"{cls.__name__} has both rows and the row-packed field(s) "
                              f"{sorted(set(unknown) & set(cls.ROWS))}")
        if unknown and peer_minor <= PROTOCOL_VERSION[1]:
            # Only a newer minor version may add fields (which this side then ignores).
            raise DecodeError(f"{cls.__name__} has unknown field(s) {unknown}; "
                              f"expected {names}")
    values = {}
    for name, convert in spec:
        if name not in body:
            if name in older:
                values[name] = older[name]
                continue
            raise DecodeError(f"{cls.__name__} lacks field {name!r}")
        try:
            if name == ROWS_KEY and packed:
                values.update(convert(body[name], peer_minor))
            else:
                values[name] = convert(body[name], peer_minor)
        except DecodeError as error:
            raise _at(f".{name}", error) from None
    return cls(**values)


def decode(data: bytes | bytearray | memoryview, expect: type[M] | tuple[type[Message], ...]
           | None = None) -> M:
    """The message in ``data``; with ``expect``, it must be one of those types.

    An :class:`ErrorReply` is always accepted (the caller decides what to raise).
    """
    return decode_with_version(data, expect)[0]


def decode_with_version(data: bytes | bytearray | memoryview,
                        expect: type[M] | tuple[type[Message], ...] | None = None
                        ) -> tuple[M, tuple[int, int]]:
    """:func:`decode`, and the protocol version the peer wrote the frame in (what it reads:
    answer it with ``encode(reply, minor)``)."""
    from .messages import ErrorReply

    if len(data) > MAX_FRAME_BYTES:
        raise DecodeError(f"frame of {len(data)} bytes exceeds the limit of {MAX_FRAME_BYTES}")
    try:
        frame = msgpack.unpackb(bytes(data), raw=False, use_list=True, strict_map_key=True,
                                max_str_len=4 * MAX_TEXT_CHARS, max_bin_len=MAX_FRAME_BYTES,
                                max_array_len=MAX_FRAME_BYTES, max_map_len=MAX_TEXT_CHARS,
                                max_ext_len=0)
    except Exception as error:  # msgpack raises many types on garbage; all mean the same
        raise DecodeError(f"not a msgpack frame ({type(error).__name__}: {error})") from None
    if not (isinstance(frame, list) and len(frame) == 4):
        raise DecodeError(f"expected a frame [major, minor, type, body], got {_kind(frame)}"
                          + (f" of length {len(frame)}" if isinstance(frame, list) else ""))
    major, minor, tag, body = frame
    if type(major) is not int or type(minor) is not int or major < 0 or minor < 0:
        raise DecodeError(f"expected non-negative integer protocol version numbers, got "
                          f"{major!r}.{minor!r}")
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
        return _build(cls, body, minor), (major, minor)
    except ProtocolError as error:
        if isinstance(error, DecodeError):
            raise _at(tag, error) from None
        raise
    except (ValueError, TypeError, OverflowError) as error:  # e.g. an absurd reshape
        raise DecodeError(f"{tag}: {error}") from None
