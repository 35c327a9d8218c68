"""How every configuration section checks its values: one error type, three checks.

A refused value raises :class:`ConfigError` (the protocol's ``BadConfig``, a ``ValueError``)
naming the field, the value that came and what is allowed; the server sends it as a
``bad_config`` reply, the commands print it as one line.
"""

from __future__ import annotations

import math

from overtake.protocol.errors import BadConfig

# A configuration value or name was refused; the message says what was expected. The
# protocol's BadConfig itself (a ValueError), so that the in-process and the remote paths
# raise one error type for one mistake.
ConfigError = BadConfig


def check(condition: bool, name: str, value: object, expected: str) -> None:
    if not condition:
        raise ConfigError(f"{name} = {value!r} is not allowed: expected {expected}")


def check_range(
    name: str,
    value: float,
    low: float | None = None,
    high: float | None = None,
    *,
    low_open: bool = False,
) -> None:
    ok = math.isfinite(value)
    if low is not None:
        ok = ok and (value > low if low_open else value >= low)
    if high is not None:
        ok = ok and value <= high
    lo = "" if low is None else (f"> {low}" if low_open else f">= {low}")
    hi = "" if high is None else f"<= {high}"
    check(ok, name, value, "a finite number " + " and ".join(p for p in (lo, hi) if p))


def check_interval(name: str, value: tuple[float, float], low: float = 0.0) -> None:
    check(
        len(value) == 2 and all(math.isfinite(v) for v in value) and low <= value[0] <= value[1],
        name,
        value,
        f"a pair (min, max) with {low} <= min <= max",
    )


def check_flag(name: str, value: object) -> None:
    check(isinstance(value, bool), name, value, "true or false")
