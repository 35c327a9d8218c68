"""Named presets: each a complete :class:`SimConfig`, the data that picks the simulation's parts
and their parameters.

Only Min et al. (2018) exists so far; Ho (2018) and Fayjie et al. (2018) are still to come.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

from .config import ConfigError, PlainValue, SimConfig, apply_overrides


def min2018() -> SimConfig:
    """Min, Kim and Huh (2018): 5 lanes, cruise 40-80 km/h, LIDAR 80 m, Table I rewards.

    The dataclass defaults are this preset; see ``../shared/notes/seed-repos.md`` for where the
    numbers come from (spawn windows 30-90 m ahead and 30-60 m behind from the authors' code).
    """
    return SimConfig(preset="min2018")


PRESETS: dict[str, Callable[[], SimConfig]] = {"min2018": min2018}
DEFAULT_PRESET = "min2018"


def make_config(
    preset: str = DEFAULT_PRESET, overrides: Mapping[str, PlainValue] | None = None
) -> SimConfig:
    """The named preset with ``overrides`` (dotted field names) applied and checked."""
    if preset not in PRESETS:
        raise ConfigError(
            f"unknown preset {preset!r}: the presets are {', '.join(sorted(PRESETS))}"
        )
    return apply_overrides(PRESETS[preset](), overrides or {})
