"""Traffic's configuration: how many cars, which driver types, and how they drive.

Each driver type (behaviour) has its share of the traffic, its range of desired speeds and its
manners (MOBIL politeness and switching threshold, how often it changes its mind about its
speed). The car-following (IDM) and lane-change (MOBIL) parameters are shared by all traffic.
The behaviours' order is :data:`~overtake.protocol.vocabulary.BEHAVIOUR_NAMES`: a vehicle's
``kind`` indexes it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from overtake.protocol.vocabulary import BEHAVIOUR_NAMES

from ..validation import check, check_flag, check_interval, check_range

Density = Literal["light", "medium", "heavy"]
DENSITIES: tuple[str, ...] = ("light", "medium", "heavy")


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

    def validate(self, name: str) -> None:
        check_range(f"{name}.share", self.share, 0.0, 1.0)
        check_interval(f"{name}.desired_speed_kmh", self.desired_speed_kmh, 1.0)
        check_range(f"{name}.politeness", self.politeness, 0.0, 1.0)
        check_range(
            f"{name}.lane_change_threshold_mps2", self.lane_change_threshold_mps2, 0.0, 10.0
        )
        check_range(f"{name}.speed_change_rate_per_s", self.speed_change_rate_per_s, 0.0, 10.0)
        check_range(
            f"{name}.random_lane_change_rate_per_s", self.random_lane_change_rate_per_s, 0.0, 10.0
        )


@dataclass(frozen=True, slots=True)
class TrafficConfig:
    """Traffic around the agents: IDM car-following, MOBIL lane changes, a treadmill of cars."""

    density: Density = "medium"
    # The traffic cars of each density, light / medium / heavy: Min et al. train and test in
    # "dense traffic" (§I.C, §IV) and the authors' slider goes up to 32 cars; chosen here: 32
    # for heavy, 20 for medium (the traffic of training: about 16 cars per km and lane on the
    # kept 250 m, where the rule driver is held well below the 80 km/h limit and a better
    # driver has room to gain, bench/RESULTS.md) and 10 for light.
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
    # random, and avoid colliding with each other in most cases. The paper gives no speeds or
    # rates; chosen here so that the 80 km/h limit is a prize a good driver often wins (the
    # reference policies' speeds in bench/RESULTS.md show it). MOBIL still makes a car leave a
    # lane it is much slower in (threshold 1 m/s^2), as the authors' cars follow or pass.
    random: BehaviourConfig = field(
        default_factory=lambda: BehaviourConfig(
            share=1.0,
            desired_speed_kmh=(40.0, 65.0),
            politeness=0.5,
            lane_change_threshold_mps2=1.0,
            speed_change_rate_per_s=0.1,
            random_lane_change_rate_per_s=0.05,
        )
    )
    # New traffic appears in these windows (metres ahead of / behind an agent) ...
    spawn_ahead_m: tuple[float, float] = (30.0, 90.0)
    spawn_behind_m: tuple[float, float] = (30.0, 60.0)
    # ... and is recycled once it is further than this from every agent.
    keep_ahead_m: float = 150.0
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
        check_range("traffic.lane_change_duration_s", self.lane_change_duration_s, 0.1, 10.0)
        check_flag("traffic.yield_to_agents", self.yield_to_agents)
        check_flag("traffic.enter_at_leader_speed", self.enter_at_leader_speed)

    @property
    def resolved_vehicle_count(self) -> int:
        """The most traffic cars on the road at once."""
        if self.vehicle_count is not None:
            return self.vehicle_count
        return self.density_vehicle_counts[DENSITIES.index(self.density)]

    @property
    def behaviours(self) -> tuple[BehaviourConfig, ...]:
        return tuple(getattr(self, name) for name in BEHAVIOUR_NAMES)
