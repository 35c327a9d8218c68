"""Named presets: each a complete :class:`SimConfig`, the data that picks the simulation's parts
and their parameters, with where every number comes from: the paper, the authors' code, or a
choice made here where both are silent.

Min et al. (2018), Ho (2018) and Fayjie et al. (2018).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping

from .assist import EgoConfig
from .config import ConfigError, PlainValue, SimConfig, apply_overrides
from .episodes import EpisodeConfig
from .rewards import RewardConfig
from .road import RoadConfig
from .sensors.action_history import ActionHistoryConfig
from .sensors.camera import CameraConfig
from .sensors.ego import EgoVectorConfig
from .sensors.grid import OccupancyGridConfig
from .sensors.lidar import LidarConfig
from .sensors.lidar_map import LidarMapConfig
from .traffic.config import BehaviourConfig, TrafficConfig


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
    - the densities: 10 / 20 / 32 traffic cars for light / medium / heavy, held on the road
      (32 is the authors' slider's most; the paper's "dense traffic" is medium's 20, where
      the rule-based driver averages well below the limit);
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


def ho2018() -> SimConfig:
    """Ho (2018), "Reinforcement Learning for Self-Driving Cars" (NTU final-year thesis).

    One reading of the thesis and his code (songyanho/Reinforcement-Learning-for-Self-Driving-
    Cars, ../shared/notes/seed-repos.md) gives every length and time: his simulator counts in
    boxes (10 px) and frames. A box is taken as one metre, which the thesis' "20 meters ahead"
    (§6.1) makes of his view's 21 boxes ahead of the bumper; his safety window of 8 boxes is
    then 8 m. His cars move 4 boxes per metre of relative travel in frames of 1/50 s
    (``car.py``): with a box of a metre that is a frame of 4/50 = 0.08 s for the speeds he
    labels in km/h, so that a speed difference moves a car as many car lengths per frame as on
    his screen, 1 km/h per frame is 3.5 m/s^2 (his 1/50 s would make it 14 m/s^2), and a
    decision every 4th frame is 0.32 s, the "human response rate" §6.1 gives as its reason
    (4 frames of 1/50 s would be 0.08 s). Where the two sources differ, that is said below.

    From the thesis:
    - a 7-lane expressway (§1, §6.1); 20 / 40 / 60 traffic cars for light / medium / heavy
      traffic (Table 4), held on the road; the three driver behaviours of Table 5 deployed at
      random (§6.1; equal shares, chosen here): ``steady`` sticks to a speed of its own,
      ``road_max`` to the maximum allowed speed, ``lane_changer`` drives at the maximum and
      switches lanes to get past whoever blocks it;
    - the actions accelerate, decelerate, keep ("maintain"), left, right (§4), a decision every
      4th frame while training (§6.1);
    - the observation: the occupancy grid of the agent's lane and the lanes either side
      (§6.1), 36 cells long (Fig. 4's 36 x 3), and the last four actions (§5's action stack);
      frames are stacked by the trainer (4, Table 6);
    - the reward (§7.2, Table 6): +1 for every car the agent passes, -1 for every car that
      passes it, each crossing counted; -0.00001 for a lane change opposite to one among the
      last four actions; no constant or emergency-brake penalty (both 0 in Table 6);
    - episodes of at most 4,000 frames (§6.1): 1,000 decisions of 4 frames;
    - an emergency brake (§6.2): a brake applied with the car ahead slower by 20 km/h or more.

    From the author's code:
    - the frames skipped between decisions repeat the decision's speed action (accelerate,
      decelerate or keep; after a lane change, keep): ``players/deep_traffic_player.py``
      moves the car by its cached action on skipped frames (``ego.skipped_frames =
      "repeat"``). Table 3 of the thesis says a decelerate is followed by three frames of
      accelerate; that reading is ``ego.skipped_frames = "table3"``. Repetition is the
      default because §4 introduces frame skipping by citing Atari's (where the action
      repeats), every other row of Table 3 repeats or ends a lane change, and his training
      charts (§7.1, §7.2) start where a random driver is under repetition (slow, negative
      scores), not under Table 3's row (fast, positive): bench/RESULTS.md. His code skips
      frames only while training: evaluation decides every frame (``gui.py``), which
      ``overtake-eval`` does for this preset (trainers/presets.py);
    - the view's cells of one box (1 m): 21 ahead of the car's front bumper, its own 7, and 8
      behind its rear (``config.py``: VISION_F 21, VISION_B 14 from the front), that is 24.5 m
      ahead of the car's centre to 11.5 m behind it (the thesis: 20 m ahead and 10 m behind);
      off-road cells read -1;
    - cars 7 boxes long (7 m) and 3.4 wide, lanes 5 boxes wide (his sprites and lane
      markings at 10 px a box);
    - the road around the agent: cars exist from 90 m ahead of the agent's front to 50 m
      behind it (``car.py``: y in [-200, 1200] px, the agent at 700) and new ones enter 80 m
      ahead or 31 m behind (``gui.py``: y = -100 and 1010), where no car is within 70-87 m
      ahead or 23-37 m behind in that lane: 140 m of road per lane, 20 car lengths;
    - the agent's speed from 0 to 110 km/h, starting at 60, changed by 1 km/h per frame
      (``ego.speed_control = "speed_steps"``); his safety rule instead of cruise control: no
      accelerating with a car within 8 m ahead, and a car there that is slower is matched at
      once; no lane change into an occupied side (``ego.lane_change_check``); traffic obeys
      the same rule behind the agent too (``traffic.yield_to_agents``), so that, as in his
      simulator, nothing collides;
    - traffic's speeds: a speed of its own drawn from 50-100 km/h (``steady``), 100 km/h for
      the other two; only the lane switcher changes lanes; traffic accelerates at 1 km/h per
      frame (3.5 m/s^2).

    Chosen here (the thesis and the code are silent):
    - lane changes of 0.24 s, 3 frames (his code jumps a lane in one frame; three keep the
      move visible to the grid and the collision test, and a change still ends within the
      decision that started it);
    - traffic's car-following (IDM) and lane changes (MOBIL): the lane switcher with politeness
      0 and threshold 0.1 m/s^2, the other two never leave their lane (threshold 10 m/s^2); a
      time headway of 0.2 s and a standstill gap of 2 m, since his cars close up to his
      8-box safety window at any speed: with more, 60 cars do not fit on 140 m of seven
      lanes (tests/test_ho2018.py holds the densities to 10%).
    """
    never = 10.0  # m/s^2: a MOBIL advantage no lane change ever reaches
    car_length_m, car_width_m = 7.0, 3.4
    return SimConfig(
        preset="ho2018",
        road=RoadConfig(lane_count=7, lane_width_m=5.0),
        traffic=TrafficConfig(
            density_vehicle_counts=(20, 40, 60),
            steady=BehaviourConfig(
                share=1.0,
                desired_speed_kmh=(50.0, 100.0),
                lane_change_threshold_mps2=never,
            ),
            road_max=BehaviourConfig(
                share=1.0,
                desired_speed_kmh=(100.0, 100.0),
                lane_change_threshold_mps2=never,
            ),
            lane_changer=BehaviourConfig(
                share=1.0,
                desired_speed_kmh=(100.0, 100.0),
                politeness=0.0,
                lane_change_threshold_mps2=0.1,
            ),
            random=dataclasses.replace(TrafficConfig().random, share=0.0),
            spawn_ahead_m=(70.0, 87.0),
            spawn_behind_m=(23.0, 37.0),
            keep_ahead_m=90.0,
            keep_behind_m=50.0,
            vehicle_length_m=car_length_m,
            vehicle_width_m=car_width_m,
            time_headway_s=0.1,
            min_gap_m=1.0,
            max_accel_mps2=3.5,
            comfort_decel_mps2=6.0,
            max_decel_mps2=15.0,
            enter_at_leader_speed=True,
            lane_change_duration_s=0.24,
            yield_to_agents=True,
        ),
        ego=EgoConfig(
            cruise_min_kmh=0.0,
            cruise_max_kmh=110.0,
            initial_speed_kmh=60.0,
            length_m=car_length_m,
            width_m=car_width_m,
            speed_control="speed_steps",
            speed_step_kmh=1.0,
            skipped_frames="repeat",
            safety_gap_m=8.0,
            lane_change_check=True,
            lane_change_duration_s=0.24,
        ),
        lidar=LidarConfig(enabled=False),
        camera=CameraConfig(enabled=False),
        ego_vector=EgoVectorConfig(enabled=False),
        grid=OccupancyGridConfig(
            enabled=True, ahead_m=24.5, behind_m=11.5, cells=36, side_lanes=1, off_road_value=-1
        ),
        action_history=ActionHistoryConfig(enabled=True),
        reward=RewardConfig(
            terms=("overtake", "passed", "alternation"),
            overtake=1.0,
            passed=-1.0,
            alternation=-0.00001,
            overtakes_counted="every_pass",
        ),
        episode=EpisodeConfig(max_decisions=1000, frames_per_decision=4, physics_dt_s=0.08),
    )


def fayjie2018() -> SimConfig:
    """Fayjie, Hossain, Oualid and Lee (2018), "Driverless Car: Autonomous Driving Using Deep
    Reinforcement Learning in Urban Environment".

    From the paper:
    - a 5-lane highway with other cars on it (§III.C);
    - the front camera in RGB at 80x80 and the LIDAR as an 80x80 grid map (§III.A, Figs. 7-8),
      4 frames of each stacked by the trainer (§III.E);
    - the actions keep going, left, right, accelerate, brake (§III.B; here keep, lane left,
      lane right, accelerate, decelerate in the simulator's action order);
    - the reward per action (§III.B): keep going the speed / 5, left -0.6, right -0.2,
      accelerate +1, brake -0.4; a hit -6. Nothing brakes for the agent: it "needs to learn
      how to accelerate when the front is empty and [...] brake when there are other cars
      [...] in front".

    Chosen here (the paper does not say; no public code of theirs is known):
    - a hit ends the episode (the paper gives its reward, not what follows it);
    - the speed in the keep-going reward in m/s, Unity's unit (0.2 per m/s: 4.4 per decision
      at 80 km/h);
    - speed control by steps (``ego.speed_control = "speed_steps"``) of 1 km/h per frame of
      0.1 s (2.8 m/s^2) while accelerate or brake is the decision, 0-100 km/h from 60, no
      safety rule and no emergency braking (``ego.safety_gap_m = 0``), and lane changes not
      refused (2 s): the agent can hit a car ahead or beside;
    - the LIDAR map's extent: 40 m ahead and 20 m either side of the car (0.5 m cells), drawn
      from a 360-ray scan of 80 m (Min et al.'s LIDAR);
    - traffic: cars that keep a speed of their own, 40-70 km/h, follow (IDM), overtake (MOBIL)
      and keep behind the agent ("cooperative", §III.C: ``traffic.yield_to_agents``); 5 / 10 /
      20 of them for light / medium / heavy (the densities Min et al.'s preset had before
      issue 32), in Min et al.'s windows;
    - a decision every 0.4 s (4 frames of 0.1 s) and episodes of at most 1,000 decisions.
    """
    return SimConfig(
        preset="fayjie2018",
        road=RoadConfig(lane_count=5),
        traffic=TrafficConfig(
            density_vehicle_counts=(5, 10, 20),
            steady=BehaviourConfig(share=1.0, desired_speed_kmh=(40.0, 70.0)),
            random=dataclasses.replace(TrafficConfig().random, share=0.0),
            yield_to_agents=True,
        ),
        ego=EgoConfig(
            cruise_min_kmh=0.0,
            cruise_max_kmh=100.0,
            initial_speed_kmh=60.0,
            speed_control="speed_steps",
            speed_step_kmh=1.0,
            skipped_frames="repeat",
            safety_gap_m=0.0,
            lane_change_check=False,
        ),
        lidar=LidarConfig(enabled=False),
        camera=CameraConfig(enabled=True, width_px=80, height_px=80, rgb=True),
        ego_vector=EgoVectorConfig(enabled=False),
        lidar_map=LidarMapConfig(
            enabled=True, cells=80, ahead_m=40.0, behind_m=0.0, half_width_m=20.0
        ),
        reward=RewardConfig(terms=("action", "collision"), collision=-6.0),
        episode=EpisodeConfig(max_decisions=1000, frames_per_decision=4, physics_dt_s=0.1),
    )


PRESETS: dict[str, Callable[[], SimConfig]] = {
    "min2018": min2018,
    "ho2018": ho2018,
    "fayjie2018": fayjie2018,
}
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
