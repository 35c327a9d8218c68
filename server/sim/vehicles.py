"""The vehicles' parameters, by kind: each traffic behaviour, then the agents' cars.

A vehicle's ``kind`` (in the state) indexes these tables; it changes only when a slot is
(re)spawned, so a decision gathers each vehicle's parameters once (:meth:`VehicleKinds.params`)
and every frame of it reads them.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from overtake.protocol.vocabulary import AGENT_KIND

from .units import KMH

if TYPE_CHECKING:
    from .assist import EgoConfig
    from .traffic.config import BehaviourConfig, TrafficConfig


def speed_walk_per_decision(
    behaviour: BehaviourConfig, decision_period_s: float
) -> tuple[float, float, float]:
    """A behaviour's speed walk as one step a decision: (step m/s, P(up), P(down)).

    The walk takes ``speed_steps_per_s`` steps a second on average, each of
    ``speed_step_kmh`` up or down with its probabilities: over a decision of ``T`` seconds
    its mean moves by ``m = r T s (up - down)`` and its square by ``v = r T s^2 (up + down)``
    (r steps a second of s). One draw a decision takes a step of ``S = s * max(1,
    sqrt(r T))`` up or down with the probabilities that give the same ``m`` and ``v + m^2``:
    exactly the walk where a decision holds at most one step (Min et al.'s 5 s against a
    decision of 0.4 s; Ho's frame when a decision is a frame), and its mean and spread
    otherwise (Ho's four frames a decision in training)."""
    if not behaviour.walks:
        return 0.0, 0.0, 0.0
    steps = behaviour.speed_steps_per_s * decision_period_s
    small = behaviour.speed_step_kmh * KMH
    big = small * max(1.0, np.sqrt(steps))
    mean = steps * small * (behaviour.speed_step_up_prob - behaviour.speed_step_down_prob)
    square = steps * small**2 * (behaviour.speed_step_up_prob + behaviour.speed_step_down_prob)
    moving = min((square + mean**2) / big**2, 1.0)
    drift = max(min(mean / big, moving), -moving)
    return big, (moving + drift) / 2, (moving - drift) / 2


@dataclass(frozen=True, slots=True)
class VehicleParams:
    """Per-vehicle (A, V) parameters of one decision, gathered from the per-kind tables."""

    headway: np.ndarray
    min_gap: np.ndarray
    max_accel: np.ndarray
    two_sqrt_ab: np.ndarray
    half_length: np.ndarray
    half_width: np.ndarray
    change_rate: np.ndarray  # lane-change progress per frame
    is_traffic: np.ndarray


class VehicleKinds:
    """Per-kind tables (one entry per traffic behaviour, then one for agents)."""

    def __init__(
        self, traffic: TrafficConfig, ego: EgoConfig, decision_period_s: float, physics_dt_s: float
    ) -> None:
        behaviours = traffic.behaviours
        self.dt = physics_dt_s

        def table(traffic_value: float, agent_value: float) -> np.ndarray:
            return np.array([traffic_value] * len(behaviours) + [agent_value])

        # Car-following (IDM): traffic's behaviours share one set, agents have their ACC's.
        self.headway = table(traffic.time_headway_s, ego.time_headway_s)
        self.min_gap = table(traffic.min_gap_m, ego.min_gap_m)
        self.accel = table(traffic.max_accel_mps2, ego.max_accel_mps2)
        self.decel = table(traffic.comfort_decel_mps2, ego.comfort_decel_mps2)
        self.two_sqrt_ab = 2.0 * np.sqrt(self.accel * self.decel)
        # Bodies and lane changes.
        self.half_length = table(traffic.vehicle_length_m / 2, ego.length_m / 2)
        self.half_width = table(traffic.vehicle_width_m / 2, ego.width_m / 2)
        self.change_duration = table(traffic.lane_change_duration_s, ego.lane_change_duration_s)
        # Traffic's manners (agents decide for themselves: zeros).
        self.politeness = np.array([b.politeness for b in behaviours] + [0.0])
        self.threshold = np.array([b.lane_change_threshold_mps2 for b in behaviours] + [0.0])
        self.speed_lo = np.array([b.desired_speed_kmh[0] * KMH for b in behaviours] + [0.0])
        self.speed_hi = np.array([b.desired_speed_kmh[1] * KMH for b in behaviours] + [0.0])
        rates = np.array([b.speed_change_rate_per_s for b in behaviours] + [0.0])
        self.change_prob = 1.0 - np.exp(-rates * decision_period_s)  # per decision
        lane_rates = np.array([b.random_lane_change_rate_per_s for b in behaviours] + [0.0])
        self.random_lane_prob = 1.0 - np.exp(-lane_rates * decision_period_s)  # per decision
        # The desired speed's random walk (per decision; BehaviourConfig.speed_steps_per_s).
        walk = [speed_walk_per_decision(b, decision_period_s) for b in behaviours]
        self.walk_step = np.array([w[0] for w in walk] + [0.0])  # m/s
        self.walk_up = np.array([w[1] for w in walk] + [0.0])
        self.walk_down = np.array([w[2] for w in walk] + [0.0])
        self.walks = bool(self.walk_step.any())
        # Its bounds (m/s); a lower bound of -1 walks from the car's own speed.
        self.walk_lo = np.array(
            [-1.0 if b.speed_walk_kmh is None else b.speed_walk_kmh[0] * KMH for b in behaviours]
            + [0.0]
        )
        self.walk_hi = np.array(
            [
                (b.desired_speed_kmh if b.speed_walk_kmh is None else b.speed_walk_kmh)[1] * KMH
                for b in behaviours
            ]
            + [0.0]
        )
        self.keeps_current = np.array([b.keeps_current_speed for b in behaviours] + [False])
        self.random_lane_when_slow = np.array(
            [b.random_lane_changes_when_slow for b in behaviours] + [False]
        )
        self.holds = bool(self.keeps_current.any())
        shares = np.array([b.share for b in behaviours])
        self.behaviour_cdf = np.cumsum(shares / shares.sum())
        self.behaviour_count = len(behaviours)
        assert self.behaviour_count == AGENT_KIND

    def behaviour_of(self, uniform: np.ndarray) -> np.ndarray:
        """The traffic behaviour a uniform draw in [0, 1) picks, by the behaviours' shares."""
        return np.minimum(
            np.searchsorted(self.behaviour_cdf, uniform, side="right"), self.behaviour_count - 1
        )

    def desired_speed(self, kind: np.ndarray, uniform: np.ndarray) -> np.ndarray:
        """A desired speed (m/s) in each kind's range, placed by a uniform draw."""
        return self.speed_lo[kind] + uniform * (self.speed_hi[kind] - self.speed_lo[kind])

    def params(self, kind: np.ndarray) -> VehicleParams:
        """Per-vehicle parameters looked up once per decision (kinds change only on spawn)."""
        return VehicleParams(
            headway=self.headway[kind],
            min_gap=self.min_gap[kind],
            max_accel=self.accel[kind],
            two_sqrt_ab=self.two_sqrt_ab[kind],
            half_length=self.half_length[kind],
            half_width=self.half_width[kind],
            change_rate=self.dt / self.change_duration[kind],
            is_traffic=kind < AGENT_KIND,
        )
