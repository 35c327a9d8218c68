"""The highway simulation core: numpy, no network, arrays in and arrays out.

Importing it loads numpy, numba and the standard library only. The rooms, each one idea on one
structure-of-arrays state:

- ``state``: the state every part reads and writes; ``randomness``: each decision's uniforms;
- ``road``: lanes and rails; ``lane_index``: who is where on the lanes;
- ``vehicles``: per-kind parameters; ``traffic``: IDM, MOBIL and random manoeuvres;
- ``assist``: the controlled car's cruise control, emergency braking and lane changes;
- ``actions``: what each discrete action asks; ``physics``: one frame of motion;
- ``spawning``: where vehicles appear; ``overtakes``: who passed whom;
- ``rewards``: the preset's reward terms; ``episodes``: episode length and metrics;
- ``sensors``: LIDAR, camera, ego vector behind one interface;
- ``config`` and ``presets``: the data that chooses all of the above;
- ``core``: :class:`HighwaySim`, which steps the parts in order; ``autoreset``: rounds with
  Gymnasium's next-step autoreset; ``render``: a top-down picture for people;
- ``kernels``: the inner loops the rooms hand to numba (same arithmetic, compiled);
  ``warm``: compiling them ahead.
"""

from .autoreset import autoreset_round
from .config import ConfigError, SimConfig, apply_overrides
from .core import HighwaySim, StepResult
from .presets import PRESETS, make_config
from .sensors.base import SensorSpace

__all__ = [
    "PRESETS",
    "ConfigError",
    "HighwaySim",
    "SensorSpace",
    "SimConfig",
    "StepResult",
    "apply_overrides",
    "autoreset_round",
    "make_config",
]
