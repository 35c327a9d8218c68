"""The simulator's compiled loops: compiled ahead by the warm-up, and cached where asked.

Their results are checked bit for bit by the golden digests (``test_golden.py``) and by the
sensors' and physics' own tests; here, that ``python -m overtake.server.sim.warm`` (run by the
container images at build time) leaves every kernel compiled in the cache.
"""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from numba.core.registry import CPUDispatcher

from overtake.server.sim import entry_kernels, kernels, lane_index_kernels, spawning_kernels
from overtake.server.sim.highway_scene import episode_kernels
from overtake.server.sim.highway_scene import kernels as scene_kernels
from overtake.server.sim.sensors import kernels as sensor_kernels
from overtake.server.sim.traffic import kernels as traffic_kernels

MODULES = (
    kernels,
    sensor_kernels,
    traffic_kernels,
    spawning_kernels,
    entry_kernels,
    lane_index_kernels,
    scene_kernels,
    episode_kernels,
)


# Slow (6 s: every kernel compiled into an empty cache); the images' build runs the same warm-up
# (tests/e2e/test_compose_e2e.py, slow too).
@pytest.mark.slow
def test_warm_up_caches_every_kernel(tmp_path):
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path)}
    done = subprocess.run(
        [sys.executable, "-m", "overtake.server.sim.warm"],
        capture_output=True,
        text=True,
        timeout=300,
        env=env,
        check=True,
    )
    assert "simulator kernels ready" in done.stdout
    cached = {path.name.split(".")[1].split("-")[0] for path in tmp_path.rglob("*kernels.*.nbi")}
    # Helpers inlined into their callers are never compiled on their own.
    compiled = {
        name
        for module in MODULES
        for name, value in vars(module).items()
        if isinstance(value, CPUDispatcher)
        and value.__module__ == module.__name__
        and value.targetoptions.get("inline") != "always"
    }
    assert compiled >= {"lidar_scan", "paint_ground", "follow_and_accelerate", "cars_ahead"}
    assert cached == compiled, f"not cached: {sorted(compiled - cached)}"
    # Each cached kernel has its compiled code beside its index.
    assert len(list(tmp_path.rglob("*kernels.*.nbc"))) >= len(compiled)
