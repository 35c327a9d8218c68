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
    """Ho's entry rule for every arena at once."""

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
        self._lanes = np.arange(road.lane_count)

    def enter(self, st: SimState, uniforms: np.ndarray) -> None:
        """This decision's entries into the free traffic slots of ``st`` (uniforms: the
        decision's (A, V, UNIFORMS_PER_VEHICLE))."""
        n = self.agents
        arenas = st.x_m.shape[0]
        rows = np.arange(arenas)
        entered = np.zeros(st.active.shape, dtype=bool)
        present = st.active[:, :n]
        # Agents off the road (a shared arena's free slots) anchor nothing, unless none is on.
        anchors = present | ~present.any(axis=1, keepdims=True)
        for attempt in range(self.tries):
            draws = uniforms[:, 0, attempt * TRY_DRAWS : (attempt + 1) * TRY_DRAWS]
            empty = ~st.active[:, n:]
            go = (draws[:, 0] < self.prob) & empty.any(axis=1)
            if not go.any():
                continue
            side = (draws[:, 1] >= 0.5).astype(np.int64)  # 0 ahead, 1 behind
            anchor = np.minimum((draws[:, 3] * n).astype(np.int64), n - 1)
            anchor = np.where(anchors[rows, anchor], anchor, np.argmax(anchors, axis=1))
            point = st.x_m[rows, anchor] + self.offset_m[side]
            zone = self.zone_m[side]
            dx = st.x_m - point[:, None]
            in_zone = st.active & (dx >= zone[:, :1]) & (dx <= zone[:, 1:])
            lanes = self._lanes[None, None, :]
            occupied = (
                in_zone[..., None]
                & ((st.lane[..., None] == lanes) | (st.target_lane[..., None] == lanes))
            ).any(axis=1)
            free = ~occupied
            count = free.sum(axis=1)
            go &= count > 0
            if not go.any():
                continue
            pick = np.minimum((draws[:, 2] * count).astype(np.int64), np.maximum(count - 1, 0))
            lane = np.argmax(np.cumsum(free, axis=1) > pick[:, None], axis=1)
            a = rows[go]
            c = n + np.argmax(empty[go], axis=1)
            own = uniforms[a, c]
            kind = self.kinds.behaviour_of(own[:, U_BEHAVIOUR])
            own_speed = self.kinds.desired_speed(kind, own[:, U_SPEED])
            low, high = self.speed_mps[side[go], 0], self.speed_mps[side[go], 1]
            speed = low + own[:, U_OFFSET] * (high - low)
            st.x_m[a, c] = point[go]
            st.lane[a, c] = st.target_lane[a, c] = lane[go]
            st.y_m[a, c] = self.road.centre_y(lane[go])
            st.change_progress[a, c] = 0.0
            st.speed_mps[a, c] = speed
            st.own_speed_mps[a, c] = own_speed
            st.desired_speed_mps[a, c] = np.maximum(own_speed, speed)
            st.accel_mps2[a, c] = 0.0
            st.kind[a, c] = kind
            st.active[a, c] = True
            entered[a, c] = True
        if entered.any():
            self.tracker.start(st, entered)
