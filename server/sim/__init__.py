"""The highway simulation core: pure numpy, no network, arrays in and arrays out."""

from .config import ConfigError, SimConfig, apply_overrides
from .core import ACTION_COUNT, ACTION_NAMES, EGO_FIELDS, METRIC_FIELDS, REWARD_TERMS, HighwaySim
from .presets import PRESETS, make_config

__all__ = ["ACTION_COUNT", "ACTION_NAMES", "EGO_FIELDS", "METRIC_FIELDS", "PRESETS",
           "REWARD_TERMS", "ConfigError", "HighwaySim", "SimConfig", "apply_overrides",
           "make_config"]
