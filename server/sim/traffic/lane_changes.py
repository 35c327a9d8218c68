"""Lane-change decisions of traffic: MOBIL (Kesting, Treiber and Helbing 2007).

A car changes lanes when its own acceleration would gain more than its behaviour's threshold,
counting the gains and losses of the followers it leaves and joins weighted by its politeness,
and when the new follower would not have to brake harder than ``traffic.safe_decel_mps2`` (under
``traffic.following = "speed_steps"``, where a follower takes a slower car's speed at once, when
the gaps ahead and behind exceed the standstill gap after a frame of closing in).
Traffic considers changing left on even decisions and right on odd ones: cars from both sides
never start into the same gap at the same moment. Decisions are taken on the first frame of a
decision, for every arena and car at once, in one compiled loop (:func:`.kernels.mobil_decide`):
the neighbours from the lane index, the accelerations and the verdict.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from overtake.protocol.vocabulary import AGENT_KIND

from ..lane_index import KEY_OFFSET, KEY_SPAN, NO_GAP_M, LaneIndex
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
        # Per kind: whether it is traffic's (agents decide their own lane changes).
        self._traffic_kind = np.arange(kinds.politeness.size) < AGENT_KIND

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
        # The state's arrays are C-ordered, so the flat views write through.
        kernels.mobil_decide(
            st.decisions,
            self._traffic_kind,
            _flat(st.kind),
            _flat(st.active),
            _flat(st.lane),
            _flat(st.target_lane),
            _flat(st.change_progress),
            self.lane_count,
            index.sorted_keys,
            index.sorted_group,
            index.sorted_vehicle,
            index.lanes_plus_one,
            KEY_SPAN,
            KEY_OFFSET,
            _flat(following.gap_m),
            _flat(following.has_leader),
            _flat(following.leader),
            _flat(random_movers),
            self.kinds.politeness,
            self.kinds.threshold,
            _flat(x_rel),
            _flat(st.speed_mps),
            _flat(st.desired_speed_mps),
            _flat(accel),
            _flat(p.headway),
            _flat(p.min_gap),
            _flat(p.max_accel),
            _flat(p.two_sqrt_ab),
            _flat(p.half_length),
            self.safe_decel_mps2,
            NO_GAP_M,
            self.react_s,
        )


def _flat(value: np.ndarray) -> np.ndarray:
    return value.reshape(-1)
