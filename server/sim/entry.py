"""Ho's way for traffic to come onto the road (``traffic.entry = "free_zone"``): a car enters
where its lane's entry zone is free, whatever the gaps around it.

His code (``gui.py``, ``gui_util.identify_free_lane``) adds at most one car a frame, with
probability one half, while the road holds fewer than its cars: the side (ahead of the agent
or behind it) drawn evenly, the lane drawn evenly among that side's lanes whose entry zone
holds no car (or no car moving into it), at 30-60 km/h ahead and 30-90 km/h behind. Each car
keeps its type and its own speed for its life, and one that enters faster than its own speed
keeps its entry speed (his cars accelerate only below their own speed). Nothing here checks
the gaps to the cars around the new one: slow cars enter a fast stream, and the traffic behind
them brakes, as in his simulator.

The simulation calls :meth:`FreeZoneEntry.enter` once per decision, after the decision's
frames, with as many tries as the decision has frames (at most :data:`MAX_ENTRY_TRIES`): a
decision of one frame (his evaluation) is exactly his frame. The tries' draws come from the
first agent's row of the decision's uniforms, whose spawn columns no spawn of an agent uses;
a new car's behaviour, own speed and entry speed from its slot's row (:mod:`.randomness`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from .entry_kernels import enter_free_zones
from .randomness import U_BEHAVIOUR, U_OFFSET, U_SPEED, UNIFORMS_PER_VEHICLE
from .units import KMH

if TYPE_CHECKING:
    from .overtakes import OvertakeTracker
    from .road import Road
    from .state import SimState
    from .traffic.config import TrafficConfig
    from .vehicles import VehicleKinds

# Draws of one try: whether it happens, the side, the lane among the free ones, the agent.
TRY_DRAWS = 4
MAX_ENTRY_TRIES = UNIFORMS_PER_VEHICLE // TRY_DRAWS


class FreeZoneEntry:
    """Ho's entry rule for every arena at once, in one compiled loop (:mod:`.entry_kernels`)."""

    def __init__(
        self,
        traffic: TrafficConfig,
        kinds: VehicleKinds,
        road: Road,
        agents: int,
        frames_per_decision: int,
        tracker: OvertakeTracker,
    ) -> None:
        self.kinds = kinds
        self.road = road
        self.agents = agents
        self.tracker = tracker
        self.tries = min(frames_per_decision, MAX_ENTRY_TRIES)
        self.prob = traffic.entry_prob_per_frame
        ahead_m, behind_m = traffic.entry_offset_m
        # Per side (0 ahead, 1 behind): the entry point from the agent, its zone, its speeds.
        self.offset_m = np.array([ahead_m, -behind_m])
        self.zone_m = np.array([traffic.entry_zone_ahead_m, traffic.entry_zone_behind_m])
        self.speed_mps = (
            np.array([traffic.entry_speed_ahead_kmh, traffic.entry_speed_behind_kmh]) * KMH
        )
        self._lane_centre_y = road.centre_y(np.arange(road.lane_count))

    def enter(self, st: SimState, uniforms: np.ndarray) -> None:
        """This decision's entries into the free traffic slots of ``st`` (uniforms: the
        decision's (A, V, UNIFORMS_PER_VEHICLE))."""
        entered = np.zeros(st.active.shape, dtype=bool)
        k = self.kinds
        if enter_free_zones(
            st.x_m, st.lane, st.target_lane, st.change_progress, st.y_m, st.speed_mps,
            st.desired_speed_mps, st.own_speed_mps, st.accel_mps2, st.kind, st.active,
            self.agents, uniforms, self.tries, TRY_DRAWS, self.prob, self.offset_m, self.zone_m,
            self.speed_mps, U_BEHAVIOUR, U_SPEED, U_OFFSET, self._lane_centre_y,
            k.behaviour_cdf, k.speed_lo, k.speed_hi, entered,
        ):  # fmt: skip
            self.tracker.start(st, entered)
