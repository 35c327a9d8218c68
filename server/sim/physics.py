"""Vehicle dynamics: one physics frame of every vehicle of every arena.

Longitudinally every car follows its leader (:mod:`.traffic.car_following`; agents through
their adaptive cruise control, :mod:`.assist`, under emergency braking), within its
acceleration limits; traffic also
never drives into traffic (a speed cap keeps it behind a traffic leader that brakes as hard as
it can, the safety rule of Ho's simulator), while an agent ahead gets no such courtesy unless
``traffic.yield_to_agents`` (ho2018, fayjie2018). Under ``ego.speed_control = "speed_steps"``
the agents' speeds are replaced by Ho's speed steps (:class:`.assist.SpeedSteps`).
Laterally a lane change is a minimum-jerk move between lane centres. A collision is an agent's
box overlapping another vehicle's. The frame's events go to the episode bookkeeping.

Car-following with the agents' assistance, the speed caps and the integration run as compiled
loops (:mod:`.kernels`): per-call numpy overhead dominated a frame at small arena counts.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .assist import CruiseControl, EmergencyBraking, SpeedSteps
from .kernels import agent_overlaps, integrate
from .lane_index import NO_GAP_M
from .lane_watch import LaneChangeWatch
from .traffic.car_following import Following
from .traffic.kernels import capped_speeds, follow_and_accelerate
from .traffic.lane_changes import Mobil
from .units import KMH

if TYPE_CHECKING:
    from .config import SimConfig
    from .episodes import EpisodeBook
    from .lane_index import LaneIndex
    from .road import Road
    from .state import SimState
    from .vehicles import VehicleKinds, VehicleParams


def min_jerk_rate(progress: np.ndarray) -> np.ndarray:
    """The rate of the minimum-jerk lateral profile (:func:`.kernels.min_jerk`) in its
    progress."""
    p = np.minimum(np.maximum(progress, 0.0), 1.0)
    return 30.0 * p * p * (1.0 - p) * (1.0 - p)


def headings(st: SimState, kinds: VehicleKinds, lane_width_m: float, agents: int) -> np.ndarray:
    """Agents' headings (A, N) in radians from the road's direction, left positive."""
    n = agents
    kind = st.kind[:, :n]
    lateral_mps = (
        (st.target_lane[:, :n] - st.lane[:, :n])
        * lane_width_m
        * min_jerk_rate(st.change_progress[:, :n])
        / kinds.change_duration[kind]
    )
    return np.arctan2(lateral_mps, np.maximum(st.speed_mps[:, :n], 1e-3))


class Physics:
    """Advances every vehicle by one frame of ``physics_dt_s``."""

    def __init__(
        self,
        config: SimConfig,
        kinds: VehicleKinds,
        road: Road,
        agents: int,
        episodes: EpisodeBook,
        watch: LaneChangeWatch | None = None,
    ) -> None:
        self.dt = config.episode.physics_dt_s
        self.max_decel_mps2 = config.traffic.max_decel_mps2
        self.lane_width_m = road.lane_width_m
        self.agents = agents
        self.cruise_control = CruiseControl(config.ego, agents)
        self.emergency_braking = EmergencyBraking(config.ego, agents)
        # Ho's speed steps and safety rule replace cruise control's speeds for the agents.
        self.speed_steps = (
            SpeedSteps(config.ego, agents) if config.ego.speed_control == "speed_steps" else None
        )
        # Whether traffic's safety rule keeps it behind agents too, not only behind traffic.
        self.yield_to_agents = config.traffic.yield_to_agents
        # Ho's speed steps for traffic (frame seconds, safety gap, whether it yields to
        # agents), or the IDM (frame 0).
        steps = config.traffic.following == "speed_steps"
        self._steps = np.array(
            [self.dt if steps else 0.0, config.traffic.safety_gap_m, float(self.yield_to_agents)]
        )
        self.mobil = Mobil(config.traffic, kinds, road.lane_count, self.dt)
        # Driver assistance watching the agents' lane changes through (the shield's option):
        # the one the lane-change assist checks starts with.
        self.watch = watch
        self.episodes = episodes
        # The kernels' parameters of cruise control and emergency braking.
        self._cruise = np.array(
            [
                self.cruise_control.time_constant_s,
                self.cruise_control.comfort_decel_mps2,
                self.cruise_control.max_accel_mps2,
            ]
        )
        self._aeb = np.array(
            [self.emergency_braking.time_to_collision_s, self.emergency_braking.decel_mps2]
        )

    def frame(
        self,
        st: SimState,
        p: VehicleParams,
        lead: np.ndarray,
        valid: np.ndarray,
        collided: np.ndarray,
        brakes: np.ndarray,
        mobil_index: LaneIndex | None,
        random_movers: np.ndarray,
        speed_command: np.ndarray | None = None,
        as_driven: np.ndarray | None = None,
    ) -> None:
        """One frame for every arena of ``st``; collisions (A, N) bool are marked in
        ``collided``, emergency brakes counted in ``brakes`` (A, N) int.

        ``lead``/``valid`` (A, 2V): each lane entry's leader; with ``mobil_index`` traffic also
        considers lane changes this frame, ``random_movers`` (A, V) whatever their incentive.
        ``speed_command`` (A, N): the agents' speed steps this frame (speed_steps control only);
        ``as_driven`` (A, N): actions to rewrite in place as the agents drove them this frame
        (:meth:`.assist.SpeedSteps.as_driven`, ``ego.applied_as_driven``).
        """
        n, dt = self.agents, self.dt
        shape = st.x_m.shape
        following = Following(
            gap_m=np.empty(shape),
            leader=np.empty(shape, dtype=np.int64),
            has_leader=np.empty(shape, dtype=bool),
            leader_speed_mps=np.empty(shape),
            closing_mps=np.empty(shape),
        )
        accel = np.empty(shape)
        # The IDM's accelerations, which MOBIL weighs (the same as ``accel`` but under Ho's
        # speed steps, whose instant matches are no measure of a lane's advantage).
        idm_accel = accel if self._steps[0] == 0.0 else np.empty(shape)
        # Car-following, the agents' cruise control and emergency braking, within limits.
        follow_and_accelerate(
            st.x_m,
            st.speed_mps,
            st.desired_speed_mps,
            lead,
            valid,
            p.half_length,
            p.headway,
            p.min_gap,
            p.max_accel,
            p.two_sqrt_ab,
            n,
            self._cruise,
            self._aeb,
            self.max_decel_mps2,
            NO_GAP_M,
            self._steps,
            following.gap_m,
            following.leader,
            following.has_leader,
            following.leader_speed_mps,
            following.closing_mps,
            accel,
            idm_accel,
        )
        if mobil_index is not None:
            x_rel = st.x_m - st.x_m[:, :1]
            self.mobil.decide(st, p, mobil_index, x_rel, idm_accel, following, random_movers)
        if self.watch is not None:
            self.watch.frame(st, accel)

        # Traffic never drives into traffic: a speed cap keeps it behind a traffic leader even
        # if that leader brakes as hard as it can (Ho's simulator has the same safety rule).
        # An agent ahead gets no such courtesy (a reckless cut-in can be rear-ended) unless
        # ``traffic.yield_to_agents`` (Ho's simulator, where every car obeys the rule).
        new_speed = np.empty(shape)
        capped_speeds(
            st.speed_mps,
            accel,
            following.gap_m,
            following.leader,
            following.has_leader,
            following.leader_speed_mps,
            p.is_traffic,
            self.yield_to_agents,
            self.max_decel_mps2,
            dt,
            new_speed,
        )
        forced = None
        if self.speed_steps is not None:
            assert speed_command is not None, "speed_steps control needs the frame's commands"
            forced = np.empty(speed_command.shape, dtype=bool)
            self.speed_steps.speeds(
                st,
                following,
                speed_command,
                self.episodes.brake_speed_diff_kmh * KMH,
                new_speed,
                forced,
            )
            if as_driven is not None:
                self.speed_steps.as_driven(st, following, as_driven)
            if not self.episodes.counts_forced_brakes:
                forced = None
        # Along the road, and laterally minimum-jerk moves between lane centres.
        integrate(
            st.speed_mps,
            new_speed,
            st.active,
            st.x_m,
            st.accel_mps2,
            st.distance_m,
            st.lane,
            st.target_lane,
            st.change_progress,
            p.change_rate,
            st.y_m,
            self.lane_width_m,
            dt,
        )
        st.frame += 1

        # The exact test, every frame and in every arena on its own. (It once ran only on
        # frames where some gap of the batch was negative: but the gaps are measured before
        # the frame's move, so a car that moved into an agent's box this frame, by a lane
        # change done within the frame (Ho's) or by closing faster than its gap, was seen a
        # frame late or, where the overlap lasted one frame, never; and whether it was seen
        # on time depended on the other arenas of the batch.)
        agent_overlaps(st.x_m, st.y_m, p.half_length, p.half_width, st.active, n, collided)
        self.episodes.note_emergency_brakes(st, following, brakes, forced)


def traffic_overlaps(st: SimState, kinds: VehicleKinds, agents: int) -> np.ndarray:
    """(A,) pairs of traffic cars whose boxes overlap now: zero in normal flow (a diagnostic;
    only agents can collide)."""
    n = agents
    x, y = st.x_m[:, n:], st.y_m[:, n:]
    kind, active = st.kind[:, n:], st.active[:, n:]
    half_l, half_w = kinds.half_length[kind], kinds.half_width[kind]
    overlap = (
        (np.abs(x[:, :, None] - x[:, None, :]) < half_l[:, :, None] + half_l[:, None, :])
        & (np.abs(y[:, :, None] - y[:, None, :]) < half_w[:, :, None] + half_w[:, None, :])
        & active[:, :, None]
        & active[:, None, :]
    )
    return np.triu(overlap, k=1).sum(axis=(1, 2))
