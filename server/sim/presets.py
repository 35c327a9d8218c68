"""Named presets: each a complete :class:`SimConfig`, the data that picks the simulation's parts
and their parameters, with where every number comes from: the paper, the authors' code, or a
choice made here where both are silent.

Min et al. (2018), Ho (2018) and Fayjie et al. (2018); and highway-env's ``highway-fast-v0`` and
``highway-v0`` (:mod:`.highway_scene.presets`).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Mapping

from overtake.protocol.vocabulary import DEFAULT_PRESET

from .assist import EgoConfig
from .config import ConfigError, PlainValue, SimConfig, apply_overrides
from .episodes import EpisodeConfig
from .highway_scene.presets import highway, highway_fast
from .rewards import RewardConfig
from .road import RoadConfig
from .sensors.action_history import ActionHistoryConfig
from .sensors.camera import CameraConfig
from .sensors.ego import EgoVectorConfig
from .sensors.grid import OccupancyGridConfig
from .sensors.lidar import LidarConfig
from .sensors.lidar_map import LidarMapConfig
from .traffic.config import NEVER_MPS2, BehaviourConfig, TrafficConfig


def min2018() -> SimConfig:
    """Min, Kim and Huh (2018), "Deep Q Learning Based High Level Driving Policy Determination".

    The dataclass defaults are this preset, with its 2,600 m episodes and its authors'
    spawners (``traffic.entry = "spawners"``; the default is the treadmill). Where each
    number comes from:

    From the paper:
    - 5 lanes (§IV.A); the five DAS-level actions (§II.C): keep (cruise control at the current
      speed v), cruise control at v + 5 km/h, at v - 5 km/h, lane change left, right
      (``ego.cruise_mode = "current"``), with cruise control and emergency braking beneath;
    - traffic spawned in a random lane near the host, acting at random (accelerate, decelerate,
      change lanes, keep) and avoiding collisions with each other in most cases (§IV.A): the
      ``random`` behaviour;
    - a 360-ray LIDAR, one ray per degree (§IV.A), and a front grey camera (§II.B);
    - the reward of Table I: the speed term linear from 40 to 80 km/h up to 1, collision -10
      (and the episode ends), lane change -0.25, overtake +0.5;
    - a decision every 4 frames (§IV.B: "the number of skipped frames is 4").

    From the authors' code (../shared/notes/seed-repos.md; files under
    ``Unity_SDK/Assets/VehicleSimulator/`` of their repository):
    - the LIDAR's 80 m range; the camera at 80x80;
    - their traffic's coming and going (``traffic.entry = "spawners"``, :mod:`.spawners`):
      the road starts empty (``Scripts/VehicleAgent.cs``: a reset destroys every car); a car
      more than 100 m from the host in a straight line leaves (``Scripts/TargetManagement.cs``,
      ``range_`` 100 in ``Prefabs/Target_*.prefab``), and so do two cars that touch (its
      ``OnTriggerEnter``); nothing is recycled. Eight spawners (``spawner_count``,
      ``Scripts/Vehicle1_Manager.cs`` .. ``Vehicle8_Manager.cs``) each keep an equal share of
      the count (the first ``count % 8`` one more); each redraws a wait of 2-7 whole seconds
      every fixed step of 0.02 s (``spawner_wait_s``, ``Random.Range(2, 8)``; ``spawner_step_s``,
      ``ProjectSettings/TimeManager.asset``) and tries once its clock passes it: a try every
      2.12 s on average (derived); a try places a car 70% of the time ahead
      (``spawner_ahead_share``, ``Random.Range(0, 1f) < 0.7f``), 30-89 m ahead or 30-59 m
      behind in whole metres (``spawn_ahead_m``, ``spawn_behind_m``: ``Random.Range(30, 90)``,
      ``Random.Range(-30, -60)``), in a lane drawn evenly, while the spawner holds fewer than
      its share and no car's centre is within 10 m along the road (``spawner_clearance_m``)
      and 10 across over their lanes 7 apart (``spawner_clearance_lanes``; ``Scene.unity``'s
      margins, ``Scripts/TargetMovement.cs``'s lane centres); so the population varies, up to
      the count;
    - the densities from their scene's slider of 0-32 cars: 20 for medium (its saved value),
      32 for heavy (its top);
    - their traffic's speeds (``TargetMovement.cs``): a car starts at 40-60 km/h and every 5 s
      steps 5 km/h, up with probability 0.75, within 40-80, so that traffic drifts towards
      the 80 km/h the host may drive; every 5 s it picks a lane change left, right or none;
    - the ego vector: left, right and forward warnings, the distance to the car ahead and its
      speed, the host's speed; acting against a warning costs -0.1 (the reward's "warning"
      term), even where the car refuses;
    - the car refuses a lane change under a side warning (``VehicleAgent.cs``: a change
      starts only with that side's warning off; their README's "Side warning: No lane
      change"): the action applied is keep (``ego.lane_change_check``); the action mask marks
      only what cannot be done at all (``ego.mask_refusals`` off: their agent chooses among
      all five actions), so that a camera-only network learns nothing of the cars beside it
      from the mask;
    - an episode ends once the host has driven 2,600 m (``VehicleAgent.cs``), or at a
      collision.

    Chosen here (the paper and the code are silent, or their way is not ours):
    - 10 traffic cars for light traffic;
    - the spawners' arithmetic once a decision (0.4 s), after its frames (theirs every fixed
      step of 0.02 s); the margin across as lane widths (10/7 of a lane: ours are 3.5 m);
      agents' cars counted in the margin too (a shared road's); at a reset each spawner's
      first try at a uniform point of one wait (theirs keep their clocks through a reset);
    - traffic's speed steps at random times, 5 s apart on average (theirs every 5 s from each
      car's start), on the desired speed of an IDM (theirs on the speed itself: a car slowed
      by the one ahead stays slow until it steps up; here it returns to its desired speed);
      MOBIL for overtaking a much slower car (threshold 1 m/s^2), braking at most 6 m/s^2;
    - cruise control's speed controller (time constant 0.5 s, 2 m/s^2 at most) and its IDM
      distance keeping (headway 1.2 s), emergency braking below 1.5 s to collision;
    - the side warnings' zone (2 m ahead of the front bumper to 4 m behind the rear, growing
      by 1 s of a closing car's speed) and the forward warning: a car ahead, no faster,
      within 2 s at the current speed (+2 m);
    - physics frames of 0.1 s, so a decision every 0.4 s; at most 1,000 decisions an episode
      besides the 2,600 m;
    - an emergency brake (Ho 2018, §6.2): a decision braking at least 1 m/s^2 with a car ahead
      slower by 20 km/h or more.
    """
    return SimConfig(
        preset="min2018",
        traffic=TrafficConfig(entry="spawners"),
        episode=EpisodeConfig(max_distance_m=2600.0),
    )


def ho2018() -> SimConfig:
    """Ho (2018), "Reinforcement Learning for Self-Driving Cars" (NTU final-year thesis).

    One reading of the thesis and his code (songyanho/Reinforcement-Learning-for-Self-Driving-
    Cars, ../shared/notes/seed-repos.md) gives every length and time: his simulator counts in
    boxes (10 px) and frames. A box is taken as one metre, which the thesis' "20 meters ahead"
    (§6.1) makes of his view's 21 boxes ahead of the bumper. His cars move 4 boxes per metre of
    relative travel in frames of 1/50 s (``car.py``): with a box of a metre that is a frame of
    4/50 = 0.08 s for the speeds he labels in km/h, so that a speed difference moves a car as
    many car lengths per frame as on his screen, 1 km/h per frame is 3.5 m/s^2 (his 1/50 s
    would make it 14 m/s^2), and a decision every 4th frame is 0.32 s, the "human response
    rate" §6.1 gives as its reason (4 frames of 1/50 s would be 0.08 s). Where the two sources
    differ, that is said below. His traffic as his code makes it: with it the rule-based driver
    makes the speeds it makes in his own code's loop (tests/papers/test_ho2018.py,
    bench/RESULTS.md).

    From the thesis:
    - a 7-lane expressway (§1, §6.1); 20 / 40 / 60 cars for light / medium / heavy traffic
      (Table 4); the three driver behaviours of Table 5 deployed at random (§6.1): ``steady``
      sticks to a speed of its own, ``road_max`` ("stick to max") wanders up to the maximum
      allowed speed, ``lane_changer`` drives at the maximum (how each drives: his code, below);
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
      ``overtake-eval`` does for this preset (trainers/config/presets.py);
    - the view's cells of one box (1 m): 21 ahead of the car's front bumper, its own 7, and 8
      behind its rear (``config.py``: VISION_F 21, VISION_B 14 from the front), that is 24.5 m
      ahead of the car's centre to 11.5 m behind it (the thesis: 20 m ahead and 10 m behind);
      off-road cells read -1;
    - cars 7 boxes long (7 m) and 3.4 wide, lanes 5 boxes wide (his sprites and lane
      markings at 10 px a box);
    - how traffic comes onto the road (``traffic.entry = "free_zone"``, ``gui.py`` and
      ``gui_util.identify_free_lane``): the road starts with the agent alone; in each frame,
      with probability one half and while it holds fewer than Table 4's cars (the agent's
      included: 19 / 39 / 59 traffic cars), a car enters 80 m ahead of the agent at 30-60 km/h
      or 31 m behind it at 30-90 km/h (centre to centre; the side drawn evenly), in a lane
      drawn among those whose entry zone is free (no car from 10 m behind to 7 m ahead of the
      entry point ahead, 6 m behind to 8 m ahead of the one behind), whatever the gaps around
      it; a car leaves the road 90 m ahead of the agent or 50 m behind it (``car.py``: y in
      [-200, 1200] px, the agent at 700): 140 m of road per lane, 20 car lengths;
    - each car's behaviour (one of the three, evenly) and its own speed (50-100 km/h) drawn
      once, when it enters (``car.py``: one of his three players; ``players/player.py``: a
      minimum speed from 50 to 99): it accelerates below its own speed, never drives over 100
      km/h, and otherwise holds the speed it has, so that a car slowed by the one ahead keeps
      the lower speed (``keeps_current_speed``) and one that entered faster keeps its entry
      speed; ``steady`` (his Player) does nothing more; ``road_max`` (his StickyPlayer) takes
      a random step of 1 km/h up or down, or none, each frame, wandering between its own
      speed and 100; ``lane_changer`` (his AggresivePlayer) steps up 1 km/h in half of the
      frames, to 100, and while slower than its own speed tries lane changes (his
      ``car_in_front`` check, whose bounds clamp to one row of his road map, 20-30 m behind
      the agent, fires whenever another car stands in the switcher's lane there: in medium
      traffic his switchers change lanes 1,400 times an episode); here it tries 3 times a
      second while slower than its own speed, into gaps that hold after a frame of closing in
      (MOBIL's gap criterion);
    - traffic follows by his rule (``traffic.following = "speed_steps"``): its speed changes by
      1 km/h a frame (3.5 m/s^2) towards its desired speed, and with a car within 3 m bumper
      to bumper ahead (``traffic.safety_gap_m``) it does not speed up, and takes a slower
      car's speed at once; the agent obeys the same rule within 4 m (``ego.safety_gap_m``).
      His check binds at a gap under 4 boxes less the fraction of a box the follower's front
      stands into its box (the rows it reads against the rows a car marks): the agent's front
      stands on a box edge (y = 700 px), so its gap is 4 m; a traffic car's moves between 3
      and 4 m as it moves, and a follower creeps up whenever the bound slips under its gap.
      Traffic obeys the rule behind the agent too (``traffic.yield_to_agents``), so that, as
      in his simulator, nothing collides;
    - lane changes within one frame, the agent's and traffic's (``check_switch_lane`` moves
      a car a whole lane in the frame it starts);
    - the agent's speed from 0 to 110 km/h, starting at 60, changed by 1 km/h per frame
      (``ego.speed_control = "speed_steps"``); no lane change into a side where a car is
      alongside (``ego.lane_change_check``; his check reads the rows of the agent's body in the
      next lane, against the rows a car marks there: a car from 2.5 m ahead of its front to
      1.5 m behind its rear, whatever its speed);
    - the action applied as his car drove it (``ego.applied_as_driven``;
      ``players/deep_traffic_player.py`` writes what ``car.move`` did over the agent's action,
      which ``deep_traffic_agent.py``'s ``remember`` stores and ``act`` pushes onto the action
      stack): in the decision's first frame, accelerate behind a car within the safety gap is
      keep, and accelerate, keep or a lane change (which still happens) with a slower car
      there is decelerate; the skipped frames repeat that action (his ``action_cache``), so a
      braked decision goes on braking 1 km/h a frame. ``info["action_applied"]`` and the
      ``actions`` observation hold it; a lane change the side check refuses is keep here (his
      player keeps the left or right it chose; the mask leaves no such choice);
    - an emergency brake counted as his ``hard_brake_count`` (``car.py``): in every frame that
      his safety rule makes the agent take the speed of a car ahead more than 20 km/h slower
      (``ego.emergency_brake_count = "forced"``; the thesis, §6.2: "20 km/h or more");
    - the grid marks a car by as many cells as it is long, from the one that holds its front
      bumper (``grid.covered_by = "near_edge"``, ``get_vision``).

    Chosen here (the thesis and the code are silent, or differ):
    - the action mask marks a lane change into a side his check refuses (``ego.mask_refusals``;
      his agent chooses among all five, and a refused one keeps its lane);
    - a new car's own and entry speeds drawn from the whole ranges, not from his integers;
      tries at entering once a decision, as many as the decision has frames (his one a frame:
      the same where a decision is a frame, as in his evaluation);
    - a ``road_max`` walk of 2 km/h steps a decision of 4 frames (the same spread as his four
      steps of 1 km/h; exactly his where a decision is a frame), a ``lane_changer``'s of 2 km/h
      a decision; the lane switcher's tries as a rate (his trigger, a car in a band behind the
      agent, tried literally, brought the rule driver no closer to his code's speeds);
    - traffic's IDM (time headway 0.1 s, standstill gap 1 m) and MOBIL remain only as what
      ``traffic.following = "idm"`` and ``traffic.entry = "comfortable"`` (the preset before
      issue 44, ``settings_history.BEFORE_AUTHORS_TRAFFIC``) use; ``comfortable`` spawns
      70-87 m ahead and 23-37 m behind.
    """
    car_length_m, car_width_m = 7.0, 3.4
    frames_per_s = 1 / 0.08  # his frame, in the time of this preset
    # What his three players share: an own speed of 50-100 km/h, the speed they have held,
    # no lane change for an advantage (NEVER_MPS2: none reaches it).
    his_player = functools.partial(
        BehaviourConfig,
        share=1.0,
        desired_speed_kmh=(50.0, 100.0),
        lane_change_threshold_mps2=NEVER_MPS2,
        keeps_current_speed=True,
    )
    return SimConfig(
        preset="ho2018",
        road=RoadConfig(lane_count=7, lane_width_m=5.0),
        traffic=TrafficConfig(
            density_vehicle_counts=(19, 39, 59),
            steady=his_player(),
            road_max=his_player(
                speed_steps_per_s=frames_per_s,
                speed_step_kmh=1.0,
                speed_step_up_prob=1 / 3,
                speed_step_down_prob=1 / 3,
            ),
            lane_changer=his_player(
                politeness=0.0,
                speed_steps_per_s=frames_per_s,
                speed_step_kmh=1.0,
                speed_step_up_prob=0.5,
                speed_step_down_prob=0.0,
                random_lane_change_rate_per_s=3.0,
                random_lane_changes_when_slow=True,
            ),
            random=dataclasses.replace(TrafficConfig().random, share=0.0),
            entry="free_zone",
            entry_prob_per_frame=0.5,
            entry_offset_m=(80.0, 31.0),
            entry_zone_ahead_m=(-10.0, 7.0),
            entry_zone_behind_m=(-6.0, 8.0),
            entry_speed_ahead_kmh=(30.0, 60.0),
            entry_speed_behind_kmh=(30.0, 90.0),
            following="speed_steps",
            safety_gap_m=3.0,
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
            lane_change_duration_s=0.08,
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
            safety_gap_m=4.0,
            emergency_brake_count="forced",
            applied_as_driven=True,
            lane_change_check=True,
            mask_refusals=True,
            lane_change_clear_ahead_m=2.5,
            lane_change_clear_behind_m=1.5,
            lane_change_closing_time_s=0.0,
            lane_change_duration_s=0.08,
        ),
        lidar=LidarConfig(enabled=False),
        camera=CameraConfig(enabled=False),
        ego_vector=EgoVectorConfig(enabled=False),
        grid=OccupancyGridConfig(
            enabled=True,
            ahead_m=24.5,
            behind_m=11.5,
            cells=36,
            side_lanes=1,
            off_road_value=-1,
            covered_by="near_edge",
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
      issue 32), spawned in Min et al.'s windows and kept 150 m ahead and 100 m behind,
      where IDM finds a comfortable gap; a car out of that range is recycled at once, on a
      side drawn evenly (``traffic.entry = "comfortable"``, the treadmill), so the road holds
      its count. Not Min et al.'s spawners (issue 68): those are their Unity scene's, while
      the paper says only that the road has other cars and no code of theirs is known; the
      density labels say how many cars are on the road, which the treadmill keeps true, and
      ``fayjie2018-fig6`` was measured on it. ``--set traffic.entry=spawners`` takes Min et
      al.'s;
    - a decision every 0.4 s (4 frames of 0.1 s) and episodes of at most 1,000 decisions.
    """
    return SimConfig(
        preset="fayjie2018",
        road=RoadConfig(lane_count=5),
        traffic=TrafficConfig(
            density_vehicle_counts=(5, 10, 20),
            steady=BehaviourConfig(share=1.0, desired_speed_kmh=(40.0, 70.0)),
            random=dataclasses.replace(TrafficConfig().random, share=0.0),
            keep_ahead_m=150.0,
            yield_to_agents=True,
            entry="comfortable",
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
    # highway-env's own scenes (highway_scene/presets.py).
    "highway-fast": highway_fast,
    "highway": highway,
}


def make_config(
    preset: str = DEFAULT_PRESET, overrides: Mapping[str, PlainValue] | None = None
) -> SimConfig:
    """The named preset with ``overrides`` (dotted field names) applied and checked."""
    if preset not in PRESETS:
        raise ConfigError(
            f"unknown preset {preset!r}: the presets are {', '.join(sorted(PRESETS))}"
        )
    return apply_overrides(PRESETS[preset](), overrides or {})
