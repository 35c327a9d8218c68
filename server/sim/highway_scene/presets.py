"""highway-env 1.12.1's ``highway-fast-v0`` and ``highway-v0`` as presets (``highway-fast``,
``highway``): the road, the cars, the frames and the episode as its ``envs/highway_env.py``
(``HighwayEnv`` and ``HighwayEnvFast``, their ``default_config``) and
``envs/common/abstract.py`` define them, highway-env's scene (:mod:`.config`) and its
Kinematics observation (:mod:`..sensors.kinematics`).

From highway-env (the file each value is in):

- a straight road of 3 (fast) / 4 lanes of 4 m (``road/lane.py``, StraightLane.DEFAULT_WIDTH;
  ``envs/highway_env.py``, lanes_count);
- 20 / 50 traffic cars (vehicles_count), every car 5 m x 2 m (``vehicle/kinematics.py``,
  Vehicle.LENGTH and WIDTH);
- physics at 5 / 15 Hz (simulation_frequency; ``envs/common/abstract.py``: 15), a decision a
  second (policy_frequency 1), so 5 / 15 frames a decision; 30 / 40 decisions an episode
  (duration, in seconds at one decision a second);
- the controlled car's spacing 1.5 / 2 (ego_spacing); traffic tested for collisions only
  against the controlled car in the fast scene (HighwayEnvFast._create_vehicles), every pair
  in the other (``road/road.py``, Road.step);
- the action mask's lane changes from the lane the car is in (``envs/common/action.py``,
  DiscreteMetaAction.get_available_actions; ``highway_scene.action_mask_lane``).

Chosen here: light and heavy traffic (this simulator's densities) are half and one and a half
times highway-env's count, which is medium's; the car's initial speed in ``ego`` (90 km/h) is
only what other parts read, the scene's ``ego_initial_speed_mps`` (25 m/s, highway-env's)
places it.
"""

from __future__ import annotations

from ..assist import EgoConfig
from ..config import SimConfig
from ..episodes import EpisodeConfig
from ..road import RoadConfig
from ..sensors.camera import CameraConfig
from ..sensors.ego import EgoVectorConfig
from ..sensors.kinematics import KinematicsConfig
from ..sensors.lidar import LidarConfig
from ..traffic.config import TrafficConfig
from .config import HighwaySceneConfig

CAR_LENGTH_M, CAR_WIDTH_M = 5.0, 2.0


def _highway(
    name: str, lanes: int, cars: int, hertz: int, decisions: int, spacing: float, collisions: str
) -> SimConfig:
    return SimConfig(
        preset=name,
        road=RoadConfig(lane_count=lanes, lane_width_m=4.0),
        traffic=TrafficConfig(
            density_vehicle_counts=(cars // 2, cars, cars * 3 // 2),
            vehicle_length_m=CAR_LENGTH_M,
            vehicle_width_m=CAR_WIDTH_M,
        ),
        ego=EgoConfig(
            length_m=CAR_LENGTH_M,
            width_m=CAR_WIDTH_M,
            initial_speed_kmh=90.0,
            cruise_min_kmh=0.0,
            cruise_max_kmh=144.0,  # Vehicle.MAX_SPEED, 40 m/s
            lane_change_check=False,
        ),
        lidar=LidarConfig(enabled=False),
        camera=CameraConfig(enabled=False),
        ego_vector=EgoVectorConfig(enabled=False),
        kinematics=KinematicsConfig(enabled=True),
        highway_scene=HighwaySceneConfig(
            enabled=True,
            ego_spacing=spacing,
            collisions=collisions,  # type: ignore[arg-type]
            action_mask_lane="current",
        ),
        episode=EpisodeConfig(
            max_decisions=decisions, frames_per_decision=hertz, physics_dt_s=1.0 / hertz
        ),
    )


def highway_fast() -> SimConfig:
    """highway-env's ``highway-fast-v0``."""
    return _highway("highway-fast", 3, 20, 5, 30, 1.5, "agents")


def highway() -> SimConfig:
    """highway-env's ``highway-v0``."""
    return _highway("highway", 4, 50, 15, 40, 2.0, "all")
