"""highway-env's highway as a scene of this simulator: its settings, each with its source.

``highway_scene.enabled`` makes an arena highway-env 1.12.1's ``highway-v0`` /
``highway-fast-v0`` (Farama's ``highway_env``, read for these facts; the code here is this
project's): its placement of the cars (``Vehicle.create_random``), its traffic (``IDMVehicle``:
IDM and MOBIL with its constants and lane-change timer), the controlled car as its
``MDPVehicle`` under ``DiscreteMetaAction`` (target speeds and lanes, followed by its speed and
steering controllers), the kinematic bicycle model every car moves by, collisions between
rotated rectangles as its ``utils.are_polygons_intersecting`` tests them, and its reward. The
road (lanes, their width), the number of cars, the episode's length and frames, and the
cars' size are the usual sections' (``road``, ``traffic``, ``episode``); the presets
``highway-fast`` and ``highway`` set them as highway-env does.

Where a value comes from is said beside it: "highway-env" with the file it is in (paths within
the ``highway_env`` package), or "chosen here".
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from ..validation import check, check_flag, check_interval, check_range


@dataclass(frozen=True, slots=True)
class HighwaySceneConfig:
    """highway-env's scene; off in the papers' presets."""

    enabled: bool = False
    # envs/highway_env.py (default_config): 1; the traffic's spacing is divided by it.
    vehicles_density: float = 1.0
    # envs/highway_env.py: 2 (highway-v0), 1.5 (highway-fast-v0): the controlled car's spacing.
    ego_spacing: float = 2.0
    # road/road.py, straight_road_network: every lane's speed limit; traffic starts at 0.7-0.8
    # of it (vehicle/kinematics.py, create_random) and the IDM never aims above it.
    speed_limit_mps: float = 30.0
    # envs/highway_env.py (_create_vehicles): the controlled car starts at 25 m/s.
    ego_initial_speed_mps: float = 25.0
    # vehicle/controller.py (MDPVehicle.DEFAULT_TARGET_SPEEDS): linspace(20, 30, 3).
    target_speeds_mps: tuple[float, ...] = (20.0, 25.0, 30.0)
    # Which pairs of cars are tested for collisions: "all" (road/road.py, Road.step) or only
    # pairs with a controlled car ("agents": highway-fast-v0 turns traffic's checks off,
    # envs/highway_env.py, HighwayEnvFast._create_vehicles).
    collisions: Literal["all", "agents"] = "all"
    # vehicle/kinematics.py (Vehicle): the speed range any car keeps within, m/s.
    max_speed_mps: float = 40.0
    # vehicle/controller.py (ControlledVehicle): the controllers' time constants (s), the
    # steering limit (rad) and the target speed step of ControlledVehicle's FASTER / SLOWER.
    tau_acceleration_s: float = 0.6
    tau_heading_s: float = 0.2
    tau_lateral_s: float = 0.6
    max_steering_rad: float = math.pi / 3
    # vehicle/behavior.py (IDMVehicle): the IDM ...
    idm_max_accel_mps2: float = 6.0
    idm_comfort_accel_mps2: float = 3.0
    idm_comfort_decel_mps2: float = -5.0
    idm_distance_wanted_m: float = 10.0  # 5 m + the car's length, centre to centre
    idm_time_wanted_s: float = 1.5
    # ... whose exponent each traffic car draws once (randomize_behavior, called by
    # envs/highway_env.py for every traffic car) ...
    idm_delta_range: tuple[float, float] = (3.5, 4.5)
    # ... and MOBIL, tried once a LANE_CHANGE_DELAY by each car's timer.
    mobil_politeness: float = 0.0
    mobil_min_accel_gain_mps2: float = 0.2
    mobil_max_braking_imposed_mps2: float = 2.0
    lane_change_delay_s: float = 1.0
    # envs/highway_env.py (default_config): the reward's terms and their weights, the speed
    # range of the high-speed term, the normalisation to [0, 1]; lane_change_reward is in
    # highway-env's configuration but its _rewards never computes the term (no effect there,
    # none here).
    collision_reward: float = -1.0
    right_lane_reward: float = 0.1
    high_speed_reward: float = 0.4
    lane_change_reward: float = 0.0
    reward_speed_range_mps: tuple[float, float] = (20.0, 30.0)
    normalize_reward: bool = True
    # envs/highway_env.py: an episode also ends when the car leaves the road (off by default).
    offroad_terminal: bool = False
    # Which lane the action mask offers lane changes from: the lane the car is in ("current":
    # envs/common/action.py, DiscreteMetaAction.get_available_actions reads the side lanes of
    # the car's lane_index, the lane nearest it), or the lane it is changing into ("target":
    # this scene before issue 68; the default, so that a configuration of before means what it
    # meant; the presets highway-fast and highway set "current"). The two differ only at a
    # decision taken while a lane change is under way next to the road's edge: at none of 272
    # decisions measured at highway-env's one decision a second, at 135 of 434 at five. What a
    # lane change does is the same either way (ControlledVehicle.act moves the target lane).
    action_mask_lane: Literal["current", "target"] = "target"
    # Who drives the controlled cars: their meta-actions (highway-env's MDPVehicle under
    # DiscreteMetaAction, the default), or the scene's own traffic model ("idm": each is
    # highway-env's IDMVehicle.create_from(its car), IDM and MOBIL with the traffic's constants
    # and its own lane-change timer; the actions sent are not read, and the action applied
    # says the meta-action each decision stands for). What overtake-eval --policy idm sets.
    ego_driver: Literal["meta_actions", "idm"] = "meta_actions"
    # vehicle/behavior.py (IDMVehicle.DELTA): the IDM exponent of a car that draws none, as
    # create_from's car does (only traffic calls randomize_behavior); read under ego_driver idm.
    ego_idm_delta: float = 4.0

    def __post_init__(self) -> None:
        check_flag("highway_scene.enabled", self.enabled)
        check_range(
            "highway_scene.vehicles_density", self.vehicles_density, 0.0, 100.0, low_open=True
        )
        check_range("highway_scene.ego_spacing", self.ego_spacing, 0.0, 100.0, low_open=True)
        check_range(
            "highway_scene.speed_limit_mps", self.speed_limit_mps, 0.0, 100.0, low_open=True
        )
        check_range("highway_scene.max_speed_mps", self.max_speed_mps, 0.0, 100.0, low_open=True)
        check_range("highway_scene.ego_initial_speed_mps", self.ego_initial_speed_mps, 0.0, 100.0)
        check(
            len(self.target_speeds_mps) >= 2
            and all(b > a for a, b in zip(self.target_speeds_mps, self.target_speeds_mps[1:]))
            and all(0.0 <= s <= 100.0 for s in self.target_speeds_mps),
            "highway_scene.target_speeds_mps",
            self.target_speeds_mps,
            "at least two increasing speeds from 0 to 100 m/s",
        )
        check(
            self.collisions in ("all", "agents"),
            "highway_scene.collisions",
            self.collisions,
            "all or agents",
        )
        check(
            self.action_mask_lane in ("current", "target"),
            "highway_scene.action_mask_lane",
            self.action_mask_lane,
            "current or target",
        )
        for name in ("tau_acceleration_s", "tau_heading_s", "tau_lateral_s", "lane_change_delay_s"):
            check_range(f"highway_scene.{name}", getattr(self, name), 0.0, 100.0, low_open=True)
        check_range(
            "highway_scene.max_steering_rad", self.max_steering_rad, 0.0, math.pi / 2, low_open=True
        )
        check_range(
            "highway_scene.idm_max_accel_mps2", self.idm_max_accel_mps2, 0.0, 50.0, low_open=True
        )
        check_range(
            "highway_scene.idm_comfort_accel_mps2",
            self.idm_comfort_accel_mps2,
            0.0,
            50.0,
            low_open=True,
        )
        check_range("highway_scene.idm_comfort_decel_mps2", self.idm_comfort_decel_mps2, -50.0, 0.0)
        check(
            self.idm_comfort_decel_mps2 < 0.0,
            "highway_scene.idm_comfort_decel_mps2",
            self.idm_comfort_decel_mps2,
            "a negative acceleration",
        )
        check_range("highway_scene.idm_distance_wanted_m", self.idm_distance_wanted_m, 0.0, 100.0)
        check_range("highway_scene.idm_time_wanted_s", self.idm_time_wanted_s, 0.0, 10.0)
        check_interval("highway_scene.idm_delta_range", self.idm_delta_range, 0.5)
        check_range("highway_scene.mobil_politeness", self.mobil_politeness, 0.0, 1.0)
        check_range(
            "highway_scene.mobil_min_accel_gain_mps2", self.mobil_min_accel_gain_mps2, -50.0, 50.0
        )
        check_range(
            "highway_scene.mobil_max_braking_imposed_mps2",
            self.mobil_max_braking_imposed_mps2,
            0.0,
            50.0,
        )
        for name in (
            "collision_reward",
            "right_lane_reward",
            "high_speed_reward",
            "lane_change_reward",
        ):
            check_range(f"highway_scene.{name}", getattr(self, name), -100.0, 100.0)
        check(
            len(self.reward_speed_range_mps) == 2
            and 0.0 <= self.reward_speed_range_mps[0] < self.reward_speed_range_mps[1] <= 100.0,
            "highway_scene.reward_speed_range_mps",
            self.reward_speed_range_mps,
            "a pair (low, high) with 0 <= low < high <= 100 m/s",
        )
        check(
            not self.normalize_reward
            or self.collision_reward < self.high_speed_reward + self.right_lane_reward,
            "highway_scene.normalize_reward",
            self.normalize_reward,
            "false where collision_reward is not below high_speed_reward + right_lane_reward "
            "(the normalisation maps that interval to [0, 1])",
        )
        check_flag("highway_scene.normalize_reward", self.normalize_reward)
        check_flag("highway_scene.offroad_terminal", self.offroad_terminal)
        check(
            self.ego_driver in ("meta_actions", "idm"),
            "highway_scene.ego_driver",
            self.ego_driver,
            "meta_actions or idm",
        )
        check(
            self.enabled or self.ego_driver == "meta_actions",
            "highway_scene.ego_driver",
            self.ego_driver,
            "meta_actions where highway_scene.enabled is false (idm drives the highway scenes' "
            "cars only: presets highway-fast and highway)",
        )
        check_range("highway_scene.ego_idm_delta", self.ego_idm_delta, 0.5, 20.0)
