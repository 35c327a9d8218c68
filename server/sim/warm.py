"""Compile the simulator's loops (:mod:`.kernels`) ahead of the first decision.

numba compiles each kernel on first use (about 3 s for all of them here) and caches the result
on disk beside the sources. A container image runs this once at build time, so that a fresh
container's first decision loads the cache instead of compiling; ``python -m
overtake.server.sim.warm`` does the same anywhere.
"""

from __future__ import annotations

import time

import numpy as np

from overtake.protocol.vocabulary import LANE_LEFT, LANE_RIGHT

from .config import PlainValue
from .core import HighwaySim
from .presets import PRESETS, make_config

# Settings whose kernels the presets' defaults leave unused: the grey camera (fayjie2018's is
# RGB) and the LIDAR scan beside the grid map.
EXTRA_SETTINGS: tuple[dict[str, PlainValue], ...] = ({"camera.rgb": False, "lidar.enabled": True},)
# ... and min2018 with the lane-change watch (its side check).
WATCH_SETTINGS: dict[str, PlainValue] = {"ego.lane_change_watch": True}


def warm_up() -> float:
    """Step every preset (and :data:`EXTRA_SETTINGS`) once, 1 and 2 arenas; returns the
    seconds it took (mostly compiling, or loading the cache)."""
    start = time.perf_counter()
    configs = [make_config(preset) for preset in sorted(PRESETS)]
    configs += [make_config("fayjie2018", settings) for settings in EXTRA_SETTINGS]
    configs.append(make_config("min2018", WATCH_SETTINGS))
    for config in configs:
        for arenas in (1, 2):
            sim = HighwaySim(config, num_arenas=arenas)
            sim.reset(seeds=list(range(arenas)))
            sim.observe()
            # Lane changes both ways (one of them starts wherever the car is), so that the
            # watch's check runs where it is on.
            for action in (LANE_LEFT, LANE_RIGHT):
                sim.step(np.full((arenas, 1), action, dtype=np.int64))
                sim.observe()
            sim.action_mask()
            sim.metrics_table()
    return time.perf_counter() - start


if __name__ == "__main__":
    print(f"simulator kernels ready in {warm_up():.1f} s")
