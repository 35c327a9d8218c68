"""Named presets: each a complete :class:`SimConfig`, the data that picks the simulation's parts
and their parameters, with where every number comes from: the paper, the authors' code, or a
choice made here where both are silent.

Only Min et al. (2018) exists so far; Ho (2018) and Fayjie et al. (2018) are still to come.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping

from .config import ConfigError, PlainValue, SimConfig, apply_overrides


def min2018() -> SimConfig:
    """Min, Kim and Huh (2018), "Deep Q Learning Based High Level Driving Policy Determination".

    The dataclass defaults are this preset. Where each number comes from:

    From the paper:
    - 5 lanes (§IV.A); the five DAS-level actions (§II.C): keep (cruise control at the current
      speed v), cruise control at v + 5 km/h, at v - 5 km/h, lane change left, right
      (``ego.cruise_mode = "current"``), with cruise control and emergency braking beneath;
    - traffic spawned in a random lane near the host, acting at random (accelerate, decelerate,
      change lanes, keep) and avoiding collisions with each other in most cases (§IV.A): the
      ``random`` behaviour;
    - a 360-ray LIDAR, one ray per degree (§IV.A), and a front grey camera (§II.B);
    - the reward of Table I: the speed term linear from 40 to 80 km/h up to 1, collision -10
      (and the episode ends), lane change -0.25, overtake +0.5.

    From the authors' code (../shared/notes/seed-repos.md):
    - the LIDAR's 80 m range; the camera at 80x80; at most 32 traffic cars (its slider);
      spawning 30-90 m ahead of or 30-60 m behind the host;
    - the ego vector: left, right and forward warnings, the distance to the car ahead and its
      speed, the host's speed; acting against a warning costs -0.1 (the reward's "warning"
      term); a lane change against a side warning is not refused (the car may collide).

    Chosen here (the paper is silent):
    - the densities: 5 / 10 / 20 traffic cars for light / medium / heavy, held on the road;
    - traffic's desired speeds, 40-65 km/h, a new one about every 10 s, a random lane change
      about every 20 s, MOBIL for overtaking a much slower car (threshold 1 m/s^2), braking at
      most 6 m/s^2: with these a privileged planner averages over 75 km/h in medium traffic,
      5 km/h more than the rule-based driver (bench/RESULTS.md);
    - traffic kept within 150 m ahead of and 100 m behind the host; when the spawn windows are
      full a car may appear anywhere in that range;
    - cruise control's speed controller (time constant 0.5 s, 2 m/s^2 at most) and its IDM
      distance keeping (headway 1.2 s), emergency braking below 1.5 s to collision;
    - the forward warning: a car ahead, no faster, within 2 s at the current speed (+2 m);
    - a decision every 0.4 s (4 physics frames of 0.1 s) and episodes of 1,000 decisions;
    - an emergency brake (Ho 2018, §6.2): a decision braking at least 1 m/s^2 with a car ahead
      slower by 20 km/h or more.
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
