"""What every message is made of: frozen records that check themselves on construction, the
limits a frame's contents are held to, and the checks the records share."""

from __future__ import annotations

import re
from dataclasses import dataclass, fields
from typing import Any, ClassVar

import numpy as np

from .errors import DecodeError

# Sizes beyond these are refused before anything is allocated.
MAX_FRAME_BYTES = 256 * 2**20
MAX_TEXT_CHARS = 65_536
MAX_ARRAY_DIMS = 5
MAX_ARENAS_PER_REQUEST = 4096
MAX_AGENTS_PER_ARENA = 48

NAME_PATTERN = re.compile(r"[A-Za-z0-9_.-]{1,64}")

# The dtypes arrays may travel in; always little-endian on the wire.
WIRE_DTYPES: dict[str, np.dtype] = {
    name: np.dtype(name).newbyteorder("<")
    for name in ("bool", "int8", "uint8", "int32", "int64", "float32", "float64")
}

Scalar = bool | int | float | str


def check_name(what: str, value: str) -> None:
    """Names end up inside Zenoh key expressions: letters, digits, ``_ . -`` only."""
    if not NAME_PATTERN.fullmatch(value):
        raise DecodeError(
            f"{what} must be 1-64 characters of letters, digits, '_', '.' or '-', got {value!r}"
        )


def check_names(what: str, names: tuple[str, ...], most: int) -> None:
    """A list of names: each a valid name, distinct, at most ``most`` of them."""
    if len(names) > most:
        raise DecodeError(f"at most {most} {what}s, got {len(names)}")
    for name in names:
        check_name(what, name)
    if len(set(names)) != len(names):
        raise DecodeError(f"{what}s must be distinct, got {list(names)}")


def check_array(what: str, value: np.ndarray, dtype: str, shape: tuple[int | None, ...]) -> None:
    """``value`` has ``dtype`` and ``shape`` (None matches any length on that axis)."""
    if value.dtype != WIRE_DTYPES[dtype]:
        raise DecodeError(f"{what} must be {dtype}, got {value.dtype}")
    if value.ndim != len(shape) or any(
        want is not None and got != want for got, want in zip(value.shape, shape, strict=True)
    ):
        wanted = "(" + ", ".join("n" if s is None else str(s) for s in shape) + ")"
        raise DecodeError(f"{what} must have shape {wanted}, got {value.shape}")


def check_range(what: str, value: int, low: int, high: int) -> None:
    if not low <= value <= high:
        raise DecodeError(f"{what} must be from {low} to {high}, got {value}")


def _values_equal(a: Any, b: Any) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return (
            isinstance(a, np.ndarray)
            and isinstance(b, np.ndarray)
            and a.dtype == b.dtype
            and a.shape == b.shape
            and np.array_equal(a, b, equal_nan=a.dtype.kind == "f")
        )
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_values_equal(a[k], b[k]) for k in a)
    if isinstance(a, (tuple, list)) and isinstance(b, (tuple, list)):
        return len(a) == len(b) and all(_values_equal(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, float) and isinstance(b, float) and a != a and b != b:
        return True  # NaN
    return type(a) is type(b) and a == b


@dataclass(frozen=True, eq=False)
class Part:
    """A frozen record that checks itself; equality compares arrays by value and dtype."""

    def __post_init__(self) -> None:
        self.check()

    def check(self) -> None:
        """Raise :class:`DecodeError` naming what is wrong. Subclasses add their rules."""

    @classmethod
    def trusted(cls, **values: Any) -> Any:
        """Build without :meth:`check`: only for records a side builds from its own arrays of
        the right dtypes and shapes, on a hot path (the server's Steps). Decoding always
        checks."""
        record = object.__new__(cls)
        for name, value in values.items():
            object.__setattr__(record, name, value)
        return record

    def __eq__(self, other: object) -> bool:
        return type(self) is type(other) and all(
            _values_equal(getattr(self, f.name), getattr(other, f.name)) for f in fields(self)
        )

    __hash__ = None  # type: ignore[assignment]


@dataclass(frozen=True, eq=False)
class Message(Part):
    """A top-level message; ``TYPE`` is its tag on the wire."""

    TYPE: ClassVar[str] = ""
