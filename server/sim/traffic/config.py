"""Traffic's configuration: how many cars, which driver types, and how they drive.

Each driver type (behaviour) has its share of the traffic, its range of desired speeds and its
manners (MOBIL politeness and switching threshold, how often it changes its mind about its
speed). The car-following (IDM) and lane-change (MOBIL) parameters are shared by all traffic.
The behaviours' order is :data:`~overtake.protocol.vocabulary.BEHAVIOUR_NAMES`: a vehicle's
``kind`` indexes it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

from overtake.protocol.vocabulary import BEHAVIOUR_NAMES, DENSITIES, Density

from ..validation import check, check_flag, check_interval, check_range

# A MOBIL threshold no advantage reaches (accelerations stay within 15 m/s^2 either way): a
# behaviour with it changes lanes only at random.
NEVER_MPS2 = 1000.0


@dataclass(frozen=True, slots=True)
class BehaviourConfig:
    """One traffic driver type: its share of the traffic, speed and manners."""

    share: float
    desired_speed_kmh: tuple[float, float]
    # MOBIL politeness p and switching threshold (m/s^2): low threshold = eager lane changer.
    politeness: float = 0.5
    lane_change_threshold_mps2: float = 0.3
    # Chance per second that a driver picks a new desired speed within its range
    # (Min et al.'s traffic randomly accelerates and brakes; 0 keeps a steady speed).
    speed_change_rate_per_s: float = 0.0
    # Chance per second that a driver changes lanes for no reason (Min et al.'s traffic
    # changes lanes at random), taken only where MOBIL's safety criterion allows it.
    random_lane_change_rate_per_s: float = 0.0
    # True (Ho's lane switcher, players/aggresive_player.py): those random lane changes are
    # tried only while the car is slower than its own speed.
    random_lane_changes_when_slow: bool = False
    # A random walk of the desired speed (Min et al.'s code: a step of 5 km/h every 5 s, up
    # with probability 0.75; Ho's "stick to max" cars: 1 km/h a frame, up, down or neither):
    # steps of speed_step_kmh, speed_steps_per_s of them a second on average, each up with
    # speed_step_up_prob and down with speed_step_down_prob (else none), within
    # speed_walk_kmh; None there walks between the car's own speed (its draw from
    # desired_speed_kmh) and the top of desired_speed_kmh. 0 steps a second: no walk.
    speed_steps_per_s: float = 0.0
    speed_step_kmh: float = 1.0
    speed_step_up_prob: float = 0.5
    speed_step_down_prob: float = 0.5
    speed_walk_kmh: tuple[float, float] | None = None
    # True (Ho's code: a car's "keep" holds the speed it has): a car slowed by the car ahead
    # keeps the lower speed as its desired speed, down to its own, until it speeds up by
    # itself (its walk); False: it returns to its desired speed when the road clears.
    keeps_current_speed: bool = False

    def validate(self, name: str) -> None:
        check_range(f"{name}.share", self.share, 0.0, 1.0)
        check_interval(f"{name}.desired_speed_kmh", self.desired_speed_kmh, 1.0)
        check_range(f"{name}.politeness", self.politeness, 0.0, 1.0)
        check_range(
            f"{name}.lane_change_threshold_mps2", self.lane_change_threshold_mps2, 0.0, NEVER_MPS2
        )
        check_range(f"{name}.speed_change_rate_per_s", self.speed_change_rate_per_s, 0.0, 10.0)
        check_range(
            f"{name}.random_lane_change_rate_per_s", self.random_lane_change_rate_per_s, 0.0, 10.0
        )
        check_range(f"{name}.speed_steps_per_s", self.speed_steps_per_s, 0.0, 100.0)
        check_range(f"{name}.speed_step_kmh", self.speed_step_kmh, 0.0, 50.0, low_open=True)
        check_range(f"{name}.speed_step_up_prob", self.speed_step_up_prob, 0.0, 1.0)
        check_range(
            f"{name}.speed_step_down_prob",
            self.speed_step_down_prob,
            0.0,
            1.0 - self.speed_step_up_prob,
        )
        check_flag(f"{name}.keeps_current_speed", self.keeps_current_speed)
        check_flag(f"{name}.random_lane_changes_when_slow", self.random_lane_changes_when_slow)
        if self.speed_walk_kmh is not None:
            check_interval(f"{name}.speed_walk_kmh", self.speed_walk_kmh, 1.0)
        # One uniform a decision serves either a new desired speed or a step of the walk.
        check(
            self.speed_change_rate_per_s == 0.0 or self.speed_steps_per_s == 0.0,
            f"{name}.speed_steps_per_s",
            self.speed_steps_per_s,
            f"0 while {name}.speed_change_rate_per_s = {self.speed_change_rate_per_s} "
            "(a car either draws new desired speeds or walks its speed, not both)",
        )

    @property
    def walks(self) -> bool:
        """Whether the desired speed takes random steps (:attr:`speed_steps_per_s`)."""
        return self.speed_steps_per_s > 0.0


@dataclass(frozen=True, slots=True)
class TrafficConfig:
    """Traffic around the agents: IDM car-following, MOBIL lane changes, and how cars come onto
    the road and leave it (``entry``: a treadmill, Ho's free zones or Min et al.'s spawners)."""

    density: Density = "medium"
    # The traffic cars of each density, light / medium / heavy: Min et al. train and test in
    # "dense traffic" (§I.C, §IV); the authors' scene has a slider of 0-32 cars, saved at 20
    # (Scene.unity; each of its eight spawners keeps its share of the slider's count): 20 for
    # medium (the slider as they left it), 32 for heavy (its top) and, chosen here, 10 for
    # light.
    density_vehicle_counts: tuple[int, int, int] = (10, 20, 32)
    # None takes the density's count; an integer overrides it.
    vehicle_count: int | None = None
    # Ho's three driver types (2018, Table 5): not in Min et al.'s traffic (share 0).
    steady: BehaviourConfig = field(
        default_factory=lambda: BehaviourConfig(
            share=0.0,
            desired_speed_kmh=(45.0, 65.0),
            politeness=0.5,
            lane_change_threshold_mps2=1.0,
            speed_change_rate_per_s=0.05,
        )
    )
    road_max: BehaviourConfig = field(
        default_factory=lambda: BehaviourConfig(
            share=0.0,
            desired_speed_kmh=(68.0, 72.0),
            politeness=0.3,
            lane_change_threshold_mps2=0.5,
        )
    )
    lane_changer: BehaviourConfig = field(
        default_factory=lambda: BehaviourConfig(
            share=0.0,
            desired_speed_kmh=(68.0, 72.0),
            politeness=0.0,
            lane_change_threshold_mps2=0.1,
        )
    )
    # Min et al.'s traffic (2018, §IV.A): cars that accelerate, decelerate and change lanes at
    # random, and avoid colliding with each other in most cases. Their code
    # (TargetMovement.cs, with the scene's "random action level" slider at 3): a car starts at
    # 40-60 km/h and every 5 s steps 5 km/h, up with probability 0.75 and down otherwise,
    # within 40-80 km/h, so that it drifts towards 80; every 5 s it picks a lane change left,
    # right or none, evenly (2/15 a second), taken only where safe. Chosen here: the steps at
    # random times (5 s apart on average; theirs every 5 s from each car's start), and MOBIL
    # still makes a car leave a lane it is much slower in (threshold 1 m/s^2).
    random: BehaviourConfig = field(
        default_factory=lambda: BehaviourConfig(
            share=1.0,
            desired_speed_kmh=(40.0, 60.0),
            politeness=0.5,
            lane_change_threshold_mps2=1.0,
            random_lane_change_rate_per_s=2 / 15,
            speed_steps_per_s=0.2,
            speed_step_kmh=5.0,
            speed_step_up_prob=0.75,
            speed_step_down_prob=0.25,
            speed_walk_kmh=(40.0, 80.0),
        )
    )
    # New traffic appears in these windows (metres ahead of / behind an agent) ...
    spawn_ahead_m: tuple[float, float] = (30.0, 90.0)
    spawn_behind_m: tuple[float, float] = (30.0, 60.0)
    # ... and is recycled (entry "comfortable") or leaves the road (the others) once it is
    # further than this from every agent: along the road, or, under entry "spawners", in a
    # straight line (Min et al.'s code, TargetManagement.cs: a car more than 100 m from the
    # host, Euclidean, destroys itself).
    keep_ahead_m: float = 100.0
    keep_behind_m: float = 100.0
    vehicle_length_m: float = 4.5
    vehicle_width_m: float = 1.8
    # IDM (Treiber et al.): time headway, standstill gap, acceleration, comfortable braking.
    time_headway_s: float = 1.5
    min_gap_m: float = 2.0
    max_accel_mps2: float = 1.5
    comfort_decel_mps2: float = 2.5
    # The hardest traffic brakes (a firm stop, not an ideal one: a car cut off too closely can
    # be hit; chosen here).
    max_decel_mps2: float = 6.0
    # MOBIL's safety criterion: a lane change may not make the new follower brake harder.
    safe_decel_mps2: float = 4.0
    lane_change_duration_s: float = 2.5
    # Traffic's safety rule (a speed cap behind a leader that brakes as hard as it can) also
    # keeps it behind the agents' cars (Ho's simulator: every car obeys it, nothing collides);
    # False (Min et al.): only behind traffic, so an agent's reckless cut-in can be rear-ended.
    yield_to_agents: bool = False
    # True: a car that enters behind a slower one enters at that one's speed (and speeds up to
    # its own when it can), as Ho's new cars enter at 30-90 km/h and accelerate; False: every
    # car enters at its desired speed, where the gaps allow that.
    enter_at_leader_speed: bool = False
    # How traffic follows: "idm" (the parameters above), or "speed_steps" (Ho's code, car.py):
    # its speed steps towards its desired speed by max_accel_mps2 at most, either way, and with
    # a vehicle ahead within safety_gap_m bumper to bumper it does not speed up and takes a
    # slower one's speed at once. The speed cap (yield_to_agents) holds under both.
    following: Literal["idm", "speed_steps"] = "idm"
    safety_gap_m: float = 3.5
    # How new traffic comes onto the road. "comfortable" (a treadmill): a car out of range is
    # recycled at once into the spawn windows above, on a side drawn evenly, where IDM finds
    # it a comfortable gap, at its desired speed (an empty slot tries again every decision),
    # and the road starts full; it holds its count where gaps allow. "spawners" (Min et al.'s
    # code, below): the road starts empty and spawners bring cars on while cars leave it, so
    # that the count is a most. "free_zone"
    # (Ho's code, gui.py): the road starts empty but for the agents; in each physics frame,
    # with probability entry_prob_per_frame and while a slot is free, one car enters at
    # entry_offset_m ahead of (first) or behind (second) an agent, centre to centre, the side
    # drawn evenly, in a lane drawn evenly among those whose entry zone holds no car (zone
    # ahead / behind: from, to, metres along the road from the entry point), at an entry speed
    # drawn from entry_speed_ahead_kmh / entry_speed_behind_kmh; it keeps a faster entry speed
    # as its desired speed (his cars only accelerate below their own speed). A car out of
    # range leaves the road, and its slot waits for an entry.
    entry: Literal["comfortable", "free_zone", "spawners"] = "comfortable"
    entry_prob_per_frame: float = 0.5
    entry_offset_m: tuple[float, float] = (80.0, 31.0)
    entry_zone_ahead_m: tuple[float, float] = (-10.0, 7.0)
    entry_zone_behind_m: tuple[float, float] = (-6.0, 8.0)
    entry_speed_ahead_kmh: tuple[float, float] = (30.0, 60.0)
    entry_speed_behind_kmh: tuple[float, float] = (30.0, 90.0)
    # Min et al.'s spawners (entry "spawners"; their Unity scene, Vehicle1_Manager.cs ..
    # Vehicle8_Manager.cs, TargetManagement.cs, VehicleAgent.cs). A reset empties the road.
    # spawner_count spawners each own an equal share of the count (the first count % spawners
    # of them one car more: their `sliderval % 8 > k`). Every fixed step of spawner_step_s a
    # spawner draws a wait of whole seconds in [spawner_wait_s) (Unity's integer
    # Random.Range, redrawn each step) and tries once its clock has passed it, then starts its
    # clock again: the waits between tries follow from these (2.12 s on average, not 2-8 s).
    # A try places a car spawner_ahead_share of the time ahead of the agent, else behind, in
    # the spawn window of that side at whole metres (Unity's integer Random.Range: 30-89 m
    # ahead, 30-59 m behind), in a lane drawn evenly, only while the spawner holds fewer cars
    # than its share and no car's centre is within spawner_clearance_m along the road and
    # spawner_clearance_lanes lane widths across (their margins of 10 over lanes 7 apart). A
    # car further than keep_ahead_m / keep_behind_m from every agent in a straight line, and
    # any two traffic cars that touch, leave the road (nothing is recycled).
    spawner_count: int = 8
    spawner_step_s: float = 0.02
    spawner_wait_s: tuple[int, int] = (2, 8)
    spawner_ahead_share: float = 0.7
    spawner_clearance_m: float = 10.0
    spawner_clearance_lanes: float = 10.0 / 7.0

    def __post_init__(self) -> None:
        check(self.density in DENSITIES, "traffic.density", self.density, f"one of {DENSITIES}")
        check(
            len(self.density_vehicle_counts) == 3
            and all(isinstance(n, int) and 0 <= n <= 200 for n in self.density_vehicle_counts),
            "traffic.density_vehicle_counts",
            self.density_vehicle_counts,
            "three integers from 0 to 200 (light, medium, heavy)",
        )
        check(
            self.vehicle_count is None
            or (isinstance(self.vehicle_count, int) and 0 <= self.vehicle_count <= 200),
            "traffic.vehicle_count",
            self.vehicle_count,
            "None or an integer from 0 to 200",
        )
        for name in BEHAVIOUR_NAMES:
            getattr(self, name).validate(f"traffic.{name}")
        total = sum(getattr(self, name).share for name in BEHAVIOUR_NAMES)
        check(
            total > 0,
            "traffic.{" + ",".join(BEHAVIOUR_NAMES) + "}.share",
            total,
            "shares that add up to more than 0",
        )
        check_interval("traffic.spawn_ahead_m", self.spawn_ahead_m)
        check_interval("traffic.spawn_behind_m", self.spawn_behind_m)
        check_range("traffic.keep_ahead_m", self.keep_ahead_m, self.spawn_ahead_m[1], 5000.0)
        check_range("traffic.keep_behind_m", self.keep_behind_m, self.spawn_behind_m[1], 5000.0)
        check_range("traffic.vehicle_length_m", self.vehicle_length_m, 2.0, 20.0)
        check_range("traffic.vehicle_width_m", self.vehicle_width_m, 1.0, 4.0)
        check_range("traffic.time_headway_s", self.time_headway_s, 0.1, 5.0)
        check_range("traffic.min_gap_m", self.min_gap_m, 0.5, 20.0)
        check_range("traffic.max_accel_mps2", self.max_accel_mps2, 0.1, 10.0)
        check_range("traffic.comfort_decel_mps2", self.comfort_decel_mps2, 0.1, 10.0)
        check_range("traffic.max_decel_mps2", self.max_decel_mps2, self.comfort_decel_mps2, 15.0)
        check_range("traffic.safe_decel_mps2", self.safe_decel_mps2, 0.1, self.max_decel_mps2)
        check_range("traffic.lane_change_duration_s", self.lane_change_duration_s, 0.01, 10.0)
        check_flag("traffic.yield_to_agents", self.yield_to_agents)
        check_flag("traffic.enter_at_leader_speed", self.enter_at_leader_speed)
        check(
            self.following in ("idm", "speed_steps"),
            "traffic.following",
            self.following,
            "idm or speed_steps",
        )
        check_range("traffic.safety_gap_m", self.safety_gap_m, 0.0, 100.0)
        check(
            self.entry in ("comfortable", "free_zone", "spawners"),
            "traffic.entry",
            self.entry,
            "comfortable, free_zone or spawners",
        )
        check(
            isinstance(self.spawner_count, int) and 1 <= self.spawner_count <= 64,
            "traffic.spawner_count",
            self.spawner_count,
            "an integer from 1 to 64",
        )
        check_range("traffic.spawner_step_s", self.spawner_step_s, 0.001, 1.0)
        low_s, high_s = self.spawner_wait_s
        check(
            len(self.spawner_wait_s) == 2
            and all(isinstance(v, int) for v in self.spawner_wait_s)
            and 0 <= low_s < high_s <= 60,
            "traffic.spawner_wait_s",
            self.spawner_wait_s,
            "two integers (first, last + 1) of whole seconds with 0 <= first < last + 1 <= 60",
        )
        check_range("traffic.spawner_ahead_share", self.spawner_ahead_share, 0.0, 1.0)
        check_range("traffic.spawner_clearance_m", self.spawner_clearance_m, 0.0, 1000.0)
        check_range("traffic.spawner_clearance_lanes", self.spawner_clearance_lanes, 0.0, 100.0)
        check_range("traffic.entry_prob_per_frame", self.entry_prob_per_frame, 0.0, 1.0)
        check_interval("traffic.entry_speed_ahead_kmh", self.entry_speed_ahead_kmh)
        check_interval("traffic.entry_speed_behind_kmh", self.entry_speed_behind_kmh)
        ahead, behind = self.entry_offset_m
        check(
            len(self.entry_offset_m) == 2
            and 0.0 <= ahead <= self.keep_ahead_m
            and 0.0 <= behind <= self.keep_behind_m,
            "traffic.entry_offset_m",
            self.entry_offset_m,
            f"(ahead, behind) within the kept road (0-{self.keep_ahead_m} m ahead, "
            f"0-{self.keep_behind_m} m behind)",
        )
        for name in ("entry_zone_ahead_m", "entry_zone_behind_m"):
            zone = getattr(self, name)
            check(
                len(zone) == 2 and all(math.isfinite(v) for v in zone) and zone[0] <= zone[1],
                f"traffic.{name}",
                zone,
                "a pair (from, to) of metres along the road, from <= to",
            )

    @property
    def resolved_vehicle_count(self) -> int:
        """The most traffic cars on the road at once."""
        if self.vehicle_count is not None:
            return self.vehicle_count
        return self.density_vehicle_counts[DENSITIES.index(self.density)]

    @property
    def behaviours(self) -> tuple[BehaviourConfig, ...]:
        return tuple(getattr(self, name) for name in BEHAVIOUR_NAMES)
