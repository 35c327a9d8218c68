"""Peer benchmark: the PyPI package highway-env on a scene comparable to ours.

Our own benchmark reports simulated seconds per wall second and per CPU second;
to make those figures meaningful it also reports them as ratios against
highway-env measured in the same run, on the same machine, under the same load.

The scene is "highway-fast-v0" with 5 lanes and 40 other vehicles, driven by
DiscreteMetaAction decisions, observing both a LIDAR and an 84x84 grayscale
image per decision, which is what our simulator produces per decision.
Random actions come from a seeded action space, so runs are repeatable.
Episode resets are inside the timed loop because our benchmark counts its
autoreset time too.

One decision advances the simulation by 1 / policy_frequency seconds, read from
the configuration the environment actually uses rather than assumed.

:func:`matched_scene` gives a second, per-preset peer: highway-env on the preset's own scene
(its lanes, traffic cars, physics and decision rates, episode length) with the observation
highway-env has closest to the preset's default sensors (chosen here: a LIDAR of as many
cells as the preset's rays and an 80x80 grey image where the preset has a LIDAR or a camera;
highway-env's occupancy grid for Ho's grid; highway-env has no RGB observation, so fayjie2018's
RGB camera is compared with a grey image).
"""

from __future__ import annotations

import os
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from bench.rates import Rates

ENV_ID = "highway-fast-v0"
IMAGE_SHAPE = (84, 84)

SCENE_CONFIG: dict[str, Any] = {
    "lanes_count": 5,
    "vehicles_count": 40,
    "action": {"type": "DiscreteMetaAction"},
    "observation": {
        "type": "TupleObservation",
        "observation_configs": [
            {
                "type": "LidarObservation",
                "cells": 16,
                "maximum_range": 60,
                "normalize": True,
            },
            {
                "type": "GrayscaleObservation",
                "observation_shape": IMAGE_SHAPE,
                "stack_size": 1,
                # ITU-R BT.601 luma weights, the usual RGB-to-gray conversion.
                "weights": [0.2989, 0.5870, 0.1140],
            },
        ],
    },
}

# The keys of the environment's final configuration that define the scene,
# reported so a printed figure says exactly what was measured.
REPORTED_CONFIG_KEYS = (
    "lanes_count",
    "vehicles_count",
    "simulation_frequency",
    "policy_frequency",
    "duration",
    "action",
    "observation",
)


@dataclass(frozen=True)
class HighwayEnvResult(Rates):
    decisions: int
    simulated_seconds: float
    wall_seconds: float
    cpu_seconds: float
    # Nested dicts are unhashable; leaving the config out of the hash keeps the
    # frozen result hashable.
    config: Mapping[str, Any] = field(hash=False)
    version: str


def matched_scene(sim_config: Any) -> dict[str, Any]:
    """highway-env's configuration for the scene of overtake's ``SimConfig``: the same lanes,
    traffic cars, physics rate, decision period and episode length, and the observation
    closest to the preset's default sensors (module docstring)."""
    episode = sim_config.episode
    observations: list[dict[str, Any]] = []
    if sim_config.grid.enabled:
        grid = sim_config.grid
        cells = grid.cells
        observations.append(
            {
                "type": "OccupancyGrid",
                "features": ["presence"],
                "grid_size": [[-grid.behind_m, grid.ahead_m], [-6.0, 6.0]],
                "grid_step": [(grid.ahead_m + grid.behind_m) / cells, 4.0],
                "absolute": False,
            }
        )
    if sim_config.lidar.enabled or sim_config.lidar_map.enabled:
        observations.append(
            {
                "type": "LidarObservation",
                "cells": sim_config.lidar.ray_count,
                "maximum_range": sim_config.lidar.max_range_m,
                "normalize": True,
            }
        )
    if sim_config.camera.enabled:
        camera = sim_config.camera
        observations.append(
            {
                "type": "GrayscaleObservation",
                "observation_shape": (camera.width_px, camera.height_px),
                "stack_size": 1,
                "weights": [0.2989, 0.5870, 0.1140],
            }
        )
    observation = (
        observations[0]
        if len(observations) == 1
        else {"type": "TupleObservation", "observation_configs": observations}
    )
    return {
        "lanes_count": sim_config.road.lane_count,
        "vehicles_count": sim_config.traffic.resolved_vehicle_count,
        "simulation_frequency": round(1.0 / episode.physics_dt_s),
        "policy_frequency": 1.0 / episode.decision_period_s,
        "duration": episode.max_decisions * episode.decision_period_s,
        "action": {"type": "DiscreteMetaAction"},
        "observation": observation,
    }


def measure_highway_env(
    decisions: int = 200, seed: int = 0, warmup: int = 10, scene: Mapping[str, Any] | None = None
) -> HighwayEnvResult:
    """Time `decisions` random decisions of highway-env after `warmup` untimed ones, on
    ``scene`` (default: :data:`SCENE_CONFIG`)."""
    # highway-env skips drawing entirely under SDL's "dummy" driver and returns
    # all-zero images; "offscreen" draws without needing a display. SDL reads
    # the variable when pygame's display is initialised, so it must be set
    # before highway-env imports and initialises pygame.
    os.environ["SDL_VIDEODRIVER"] = "offscreen"
    try:
        import gymnasium
        import highway_env
    except ImportError as error:
        raise RuntimeError(
            "highway-env is not installed; install the bench extra with `pip install -e '.[bench]'`"
        ) from error

    config = dict(SCENE_CONFIG if scene is None else scene)
    env = gymnasium.make(ENV_ID, config=config)
    try:
        first = env.reset(seed=seed)[0]
        drawn = config["observation"]["type"] in ("TupleObservation", "GrayscaleObservation")
        image = first[-1] if isinstance(first, tuple) else first
        if drawn and not np.any(image):
            raise RuntimeError(
                "highway-env rendered an all-zero grayscale image; pygame is not "
                "drawing (check SDL_VIDEODRIVER, which must not be 'dummy')"
            )
        env.action_space.seed(seed)
        used_config = env.unwrapped.config
        seconds_per_decision = 1.0 / used_config["policy_frequency"]

        def decide(count: int) -> None:
            for _ in range(count):
                _, _, terminated, truncated, _ = env.step(env.action_space.sample())
                if terminated or truncated:
                    env.reset()

        decide(warmup)
        wall_start, cpu_start = time.perf_counter(), time.process_time()
        decide(decisions)
        wall_seconds = time.perf_counter() - wall_start
        cpu_seconds = time.process_time() - cpu_start
    finally:
        env.close()

    return HighwayEnvResult(
        decisions=decisions,
        simulated_seconds=decisions * seconds_per_decision,
        wall_seconds=wall_seconds,
        cpu_seconds=cpu_seconds,
        config={key: used_config[key] for key in REPORTED_CONFIG_KEYS},
        version=highway_env.__version__,
    )


if __name__ == "__main__":
    result = measure_highway_env()
    print(f"highway-env {result.version} {ENV_ID} config: {result.config}")
    print(f"decisions: {result.decisions}")
    print(f"sim s: {result.simulated_seconds:.3f}")
    print(f"wall s: {result.wall_seconds:.3f}")
    print(f"cpu s: {result.cpu_seconds:.3f}")
    print(f"sim s per wall s: {result.sim_seconds_per_wall_second:.3f}")
    print(f"sim s per CPU s: {result.sim_seconds_per_cpu_second:.3f}")
