"""Driver assistance: what the controlled car does beneath the agent's decisions.

Min et al.'s agents act at the level of a driver-assistance system (DAS): adaptive cruise
control holds the cruise target (the IDM of :mod:`.traffic.car_following`, with the car's own
parameters), autonomous emergency braking takes over when the time to collision gets short,
lane keeping holds the lane, and a lane change, once asked for, is a smooth lateral move that
driver assistance starts only into a clear lane (Min et al.'s cars change lanes only without a
side warning). :class:`EgoConfig` holds the car's body and all of these parameters.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from .units import KMH
from .validation import check_range

if TYPE_CHECKING:
    from .state import SimState
    from .traffic.car_following import Following
    from .vehicles import VehicleKinds


@dataclass(frozen=True, slots=True)
class EgoConfig:
    """The controlled car: DAS functions (adaptive cruise, lane keeping, AEB) under the actions."""

    cruise_min_kmh: float = 40.0
    cruise_max_kmh: float = 80.0
    cruise_step_kmh: float = 5.0
    initial_speed_kmh: float = 60.0
    length_m: float = 4.5
    width_m: float = 1.8
    # Adaptive cruise control is an IDM with these parameters and the cruise target as v0.
    time_headway_s: float = 1.2
    min_gap_m: float = 2.0
    max_accel_mps2: float = 2.0
    comfort_decel_mps2: float = 3.0
    # Autonomous emergency braking: full braking when the time to collision falls below this.
    aeb_time_to_collision_s: float = 1.5
    aeb_decel_mps2: float = 8.0
    # Ho's emergency brake: braking at least this hard (m/s^2) ...
    emergency_decel_mps2: float = 4.0
    # ... with at least this speed difference to the car ahead (Ho 2018, section 6.2).
    emergency_speed_diff_kmh: float = 20.0
    lane_change_duration_s: float = 2.0
    # Driver assistance refuses to start a lane change into a lane that is not clear from
    # lane_change_clear_behind_m behind to lane_change_clear_ahead_m ahead, bumper to bumper,
    # counting cars already moving into it (the action mask says so): Min et al.'s cars change
    # lanes only without a side warning. Each window grows by the closing speed of a car there
    # times lane_change_closing_time_s: a car 10 m/s faster behind needs 10 m more. False lets
    # every change start, whoever is beside.
    lane_change_check: bool = True
    lane_change_clear_ahead_m: float = 2.0
    lane_change_clear_behind_m: float = 4.0
    lane_change_closing_time_s: float = 1.0

    def __post_init__(self) -> None:
        check_range("ego.cruise_min_kmh", self.cruise_min_kmh, 0.0, 300.0)
        check_range("ego.cruise_max_kmh", self.cruise_max_kmh, self.cruise_min_kmh, 300.0)
        check_range("ego.cruise_step_kmh", self.cruise_step_kmh, 0.0, 50.0, low_open=True)
        check_range(
            "ego.initial_speed_kmh",
            self.initial_speed_kmh,
            self.cruise_min_kmh,
            self.cruise_max_kmh,
        )
        check_range("ego.length_m", self.length_m, 2.0, 20.0)
        check_range("ego.width_m", self.width_m, 1.0, 3.0)
        check_range("ego.time_headway_s", self.time_headway_s, 0.1, 5.0)
        check_range("ego.min_gap_m", self.min_gap_m, 0.5, 20.0)
        check_range("ego.max_accel_mps2", self.max_accel_mps2, 0.1, 10.0)
        check_range("ego.comfort_decel_mps2", self.comfort_decel_mps2, 0.1, 10.0)
        check_range("ego.aeb_time_to_collision_s", self.aeb_time_to_collision_s, 0.0, 10.0)
        check_range("ego.aeb_decel_mps2", self.aeb_decel_mps2, 0.1, 15.0)
        check_range("ego.emergency_decel_mps2", self.emergency_decel_mps2, 0.1, 15.0)
        check_range("ego.emergency_speed_diff_kmh", self.emergency_speed_diff_kmh, 0.0, 300.0)
        check_range("ego.lane_change_duration_s", self.lane_change_duration_s, 0.5, 10.0)
        check_range("ego.lane_change_clear_ahead_m", self.lane_change_clear_ahead_m, 0.0, 100.0)
        check_range("ego.lane_change_clear_behind_m", self.lane_change_clear_behind_m, 0.0, 100.0)
        check_range("ego.lane_change_closing_time_s", self.lane_change_closing_time_s, 0.0, 10.0)


class CruiseControl:
    """The agents' cruise targets (``desired_speed_mps`` of their columns), within limits."""

    def __init__(self, ego: EgoConfig, agents: int) -> None:
        self.min_mps = ego.cruise_min_kmh * KMH
        self.max_mps = ego.cruise_max_kmh * KMH
        self.agents = agents

    def adjust(self, st: SimState, change_mps: np.ndarray) -> None:
        """Move each agent's target by ``change_mps`` (A, N), clipped to the cruise range."""
        cruise = st.desired_speed_mps[:, : self.agents]
        cruise += change_mps
        np.minimum(np.maximum(cruise, self.min_mps, out=cruise), self.max_mps, out=cruise)


class EmergencyBraking:
    """Autonomous emergency braking: full braking when the time to collision gets short."""

    def __init__(self, ego: EgoConfig, agents: int) -> None:
        self.time_to_collision_s = ego.aeb_time_to_collision_s
        self.decel_mps2 = ego.aeb_decel_mps2
        self.agents = agents

    def apply(self, accel: np.ndarray, following: Following) -> None:
        """Brake the agents that close in on their leader too fast (``accel`` in place)."""
        n = self.agents
        agent_closing = following.closing_mps[:, :n]
        aeb = (agent_closing > 0.0) & (
            following.gap_m[:, :n] < agent_closing * self.time_to_collision_s
        )
        if aeb.any():
            accel[:, :n] = np.where(aeb, np.minimum(accel[:, :n], -self.decel_mps2), accel[:, :n])


class LaneChangeAssist:
    """Starts the agents' lane changes, and says which it would start now.

    A change needs a lane on that side and no change under way; with ``ego.lane_change_check``
    also a clear side (:meth:`side_clear`), and of two agents cleared into the same gap at the
    same decision only the lower-numbered one goes.
    """

    def __init__(self, ego: EgoConfig, kinds: VehicleKinds, lane_count: int, agents: int) -> None:
        self.ego = ego
        self.kinds = kinds
        self.lane_count = lane_count
        self.agents = agents

    def possible(self, st: SimState) -> tuple[np.ndarray, np.ndarray]:
        """(A, N) bool each, left and right: a lane there and no change under way."""
        n = self.agents
        lane = st.lane[:, :n]
        idle = st.target_lane[:, :n] == lane
        return idle & (lane < self.lane_count - 1), idle & (lane > 0)

    def allowed(self, st: SimState) -> tuple[np.ndarray, np.ndarray]:
        """(A, N) bool each, left and right: a change that would start now if asked for."""
        left, right = self.possible(st)
        if self.ego.lane_change_check:
            clear = self.side_clear(st)
            left &= clear[..., 1]
            right &= clear[..., 0]
        return left, right

    def start(self, st: SimState, want_left: np.ndarray, want_right: np.ndarray) -> np.ndarray:
        """Start the asked-for changes (A, N) that are allowed; returns which started."""
        n = self.agents
        left, right = self.possible(st)
        go_left = want_left & left
        go_right = want_right & right
        if self.ego.lane_change_check and (go_left | go_right).any():
            clear = self.side_clear(st)
            go_left &= clear[..., 1]
            go_right &= clear[..., 0]
            if n > 1:
                self._one_agent_per_gap(st, go_left, go_right)
        started = go_left | go_right
        st.target_lane[:, :n] += go_left.astype(np.int64) - go_right
        st.change_progress[:, :n] = np.where(started, 0.0, st.change_progress[:, :n])
        return started

    def side_clear(self, st: SimState) -> np.ndarray:
        """(A, N, 2) bool: whether the lane to each agent's right [0] and left [1] is clear for
        starting a lane change: no other vehicle in it, or moving into it, from
        ``lane_change_clear_behind_m`` behind the agent's rear bumper to
        ``lane_change_clear_ahead_m`` ahead of its front bumper, each window growing by the
        speed at which a car there closes in times ``lane_change_closing_time_s``. A lane that
        does not exist counts as clear here; :meth:`possible` refuses it anyway."""
        n, ego = self.agents, self.ego
        half = self.kinds.half_length[st.kind]  # (A, V)
        dx = st.x_m[:, None, :] - st.x_m[:, :n, None]  # (A, N, V): other - agent
        reach = half[:, None, :] + half[:, :n, None]
        # Positive when the other car gains on the agent from behind (or the agent on a car
        # ahead): the gap it needs grows with that speed.
        closing_mps = st.speed_mps[:, None, :] - st.speed_mps[:, :n, None]
        ahead_m = (
            ego.lane_change_clear_ahead_m
            + np.maximum(-closing_mps, 0.0) * ego.lane_change_closing_time_s
        )
        behind_m = (
            ego.lane_change_clear_behind_m
            + np.maximum(closing_mps, 0.0) * ego.lane_change_closing_time_s
        )
        near = (dx - reach < ahead_m) & (-dx - reach < behind_m)
        near &= st.active[:, None, :]
        near[:, np.arange(n), np.arange(n)] = False  # not the agent itself
        clear = np.empty(near.shape[:2] + (2,), dtype=bool)
        for side, step in enumerate((-1, 1)):
            lane = (st.lane[:, :n] + step)[:, :, None]
            there = (st.lane[:, None, :] == lane) | (st.target_lane[:, None, :] == lane)
            clear[..., side] = ~(near & there).any(axis=2)
        return clear

    def _one_agent_per_gap(self, st: SimState, go_left: np.ndarray, go_right: np.ndarray) -> None:
        """Agents cleared into the same lane at the same decision, near each other (from
        opposite sides), would meet there: the lower-numbered agent goes, the other keeps its
        lane. Changes ``go_left``/``go_right`` (A, N) in place."""
        n, ego = self.agents, self.ego
        started = go_left | go_right
        if not (started.sum(axis=1) > 1).any():
            return
        target = st.lane[:, :n] + go_left.astype(np.int64) - go_right
        half = self.kinds.half_length[st.kind[:, :n]]
        dx = np.abs(st.x_m[:, None, :n] - st.x_m[:, :n, None]) - half[:, None, :] - half[:, :, None]
        window = max(ego.lane_change_clear_ahead_m, ego.lane_change_clear_behind_m)
        lower = np.tri(n, k=-1, dtype=bool)  # [i, j]: j < i
        conflict = (
            lower
            & (dx < window)
            & started[:, None, :]
            & started[:, :, None]
            & (target[:, None, :] == target[:, :, None])
        )
        yields = conflict.any(axis=2)
        go_left &= ~yields
        go_right &= ~yields
