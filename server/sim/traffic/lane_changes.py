"""Lane-change decisions of traffic: MOBIL (Kesting, Treiber and Helbing 2007).

A car changes lanes when its own acceleration would gain more than its behaviour's threshold,
counting the gains and losses of the followers it leaves and joins weighted by its politeness,
and when the new follower would not have to brake harder than ``traffic.safe_decel_mps2`` (under
``traffic.following = "speed_steps"``, where a follower takes a slower car's speed at once, when
the gaps ahead and behind exceed the standstill gap after a frame of closing in).
Traffic considers changing left on even decisions and right on odd ones: cars from both sides
never start into the same gap at the same moment. Decisions are taken on the first frame of a
decision, for every arena and car at once: the neighbours from the lane index in numpy, the
accelerations and the verdict in a compiled loop (:func:`.kernels.mobil_accept`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..lane_index import NO_GAP_M, LaneIndex, neighbours_at
from . import kernels
from .car_following import Following

if TYPE_CHECKING:
    from ..state import SimState
    from ..vehicles import VehicleKinds, VehicleParams
    from .config import TrafficConfig


class Mobil:
    """MOBIL for every traffic car of every arena."""

    def __init__(
        self, traffic: TrafficConfig, kinds: VehicleKinds, lane_count: int, frame_s: float
    ) -> None:
        self.kinds = kinds
        self.lane_count = lane_count
        # Under Ho's speed steps a follower takes a slower car's speed at once, however hard
        # that brakes: a change is safe where the gaps are (his check: no car alongside).
        steps = traffic.following == "speed_steps"
        self.safe_decel_mps2 = np.inf if steps else traffic.safe_decel_mps2
        # ... where they still are after the frame of closing in that passes before the cars
        # around see the change (a change is done within its frame there).
        self.react_s = frame_s if steps else 0.0

    def decide(
        self,
        st: SimState,
        p: VehicleParams,
        index: LaneIndex,
        x_rel: np.ndarray,
        accel: np.ndarray,
        following: Following,
        random_movers: np.ndarray,
    ) -> None:
        """Start the lane changes MOBIL accepts (``target_lane`` and ``change_progress``).

        ``accel`` (A, V) is this frame's acceleration of every car in its current lane,
        ``following`` whom each follows, ``index`` the lanes' order at the decision's start;
        ``random_movers`` (A, V) the cars that change lanes whatever their incentive, where
        the safety criterion allows (Min et al.'s random lane changes).
        """
        direction = np.where(st.decisions % 2 == 0, 1, -1)
        target = st.lane + direction[:, None]
        candidate = (
            p.is_traffic
            & st.active
            & (st.target_lane == st.lane)
            & (target >= 0)
            & (target < self.lane_count)
        )
        flat = np.flatnonzero(candidate)
        if flat.size == 0:
            return
        vehicles = st.x_m.shape[1]
        arena = flat // vehicles
        xf = x_rel.reshape(-1)
        new_lane = target.reshape(-1)[flat]
        new_leader, new_follower = neighbours_at(index, arena, new_lane, xf[flat])
        _, old_follower = neighbours_at(index, arena, st.lane.reshape(-1)[flat], xf[flat])
        kind = st.kind.reshape(-1)[flat]
        accept = kernels.mobil_accept(
            flat,
            new_leader,
            new_follower,
            old_follower,
            following.gap_m.reshape(-1)[flat],
            following.has_leader.reshape(-1)[flat],
            following.leader.reshape(-1)[flat],
            random_movers.reshape(-1)[flat],
            self.kinds.politeness[kind],
            self.kinds.threshold[kind],
            np.ascontiguousarray(xf),
            st.speed_mps.reshape(-1),
            st.desired_speed_mps.reshape(-1),
            accel.reshape(-1),
            np.ascontiguousarray(p.headway.reshape(-1)),
            np.ascontiguousarray(p.min_gap.reshape(-1)),
            np.ascontiguousarray(p.max_accel.reshape(-1)),
            np.ascontiguousarray(p.two_sqrt_ab.reshape(-1)),
            np.ascontiguousarray(p.half_length.reshape(-1)),
            self.safe_decel_mps2,
            NO_GAP_M,
            self.react_s,
        )
        st.target_lane.reshape(-1)[flat[accept]] = new_lane[accept]
        st.change_progress.reshape(-1)[flat[accept]] = 0.0
