"""Lane-change decisions of traffic: MOBIL (Kesting, Treiber and Helbing 2007).

A car changes lanes when its own acceleration would gain more than its behaviour's threshold,
counting the gains and losses of the followers it leaves and joins weighted by its politeness,
and when the new follower would not have to brake harder than ``traffic.safe_decel_mps2``.
Traffic considers changing left on even decisions and right on odd ones: cars from both sides
never start into the same gap at the same moment. Decisions are taken on the first frame of a
decision, for every arena and car at once.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..lane_index import NO_GAP_M, LaneIndex, neighbours_at
from .car_following import Following, idm_accel

if TYPE_CHECKING:
    from ..state import SimState
    from ..vehicles import VehicleKinds, VehicleParams
    from .config import TrafficConfig


class Mobil:
    """MOBIL for every traffic car of every arena."""

    def __init__(self, traffic: TrafficConfig, kinds: VehicleKinds, lane_count: int) -> None:
        self.kinds = kinds
        self.lane_count = lane_count
        self.safe_decel_mps2 = traffic.safe_decel_mps2

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
        g = {
            name: getattr(p, name).reshape(-1)
            for name in ("headway", "min_gap", "max_accel", "two_sqrt_ab", "half_length")
        }
        xf, vf = x_rel.reshape(-1), st.speed_mps.reshape(-1)
        v0f, af = st.desired_speed_mps.reshape(-1), accel.reshape(-1)

        def idm(i: np.ndarray, gap_m: np.ndarray, closing: np.ndarray) -> np.ndarray:
            return idm_accel(
                vf[i],
                v0f[i],
                gap_m,
                closing,
                g["headway"][i],
                g["min_gap"][i],
                g["max_accel"][i],
                g["two_sqrt_ab"][i],
            )

        x, v, half = xf[flat], vf[flat], g["half_length"][flat]
        new_lane = target.reshape(-1)[flat]
        new_leader, new_follower = neighbours_at(index, arena, new_lane, x)
        _, old_follower = neighbours_at(index, arena, st.lane.reshape(-1)[flat], x)

        has_nl = new_leader >= 0
        nl = np.maximum(new_leader, 0)
        gap_new = np.where(has_nl, xf[nl] - x - g["half_length"][nl] - half, NO_GAP_M)
        accel_new = idm(flat, gap_new, np.where(has_nl, v - vf[nl], 0.0))

        has_nf = new_follower >= 0
        nf = np.maximum(new_follower, 0)
        gap_nf = np.where(has_nf, x - xf[nf] - half - g["half_length"][nf], NO_GAP_M)
        nf_accel_new = idm(nf, gap_nf, vf[nf] - v)
        nf_gain = np.where(has_nf, nf_accel_new - af[nf], 0.0)

        # The old follower would follow the old leader across the gap this car leaves.
        has_of = old_follower >= 0
        of = np.maximum(old_follower, 0)
        own_gap = following.gap_m.reshape(-1)[flat]
        own_has_leader = following.has_leader.reshape(-1)[flat]
        of_gap_after = np.where(own_has_leader, own_gap + 2 * half, NO_GAP_M) + (
            x - xf[of] - half - g["half_length"][of]
        )
        ol_speed = np.where(own_has_leader, vf[following.leader.reshape(-1)[flat]], vf[of])
        of_gain = np.where(has_of, idm(of, of_gap_after, vf[of] - ol_speed) - af[of], 0.0)

        kind = st.kind.reshape(-1)[flat]
        min_gap = g["min_gap"][flat]
        safe = (
            (gap_new > min_gap)
            & (gap_nf > min_gap)
            & (~has_nf | (nf_accel_new >= -self.safe_decel_mps2))
        )
        incentive = accel_new - af[flat] + self.kinds.politeness[kind] * (nf_gain + of_gain)
        # A change for no reason must not make the mover itself brake hard either.
        random = random_movers.reshape(-1)[flat] & (accel_new >= -self.safe_decel_mps2)
        accept = safe & ((incentive > self.kinds.threshold[kind]) | random)
        st.target_lane.reshape(-1)[flat[accept]] = new_lane[accept]
        st.change_progress.reshape(-1)[flat[accept]] = 0.0
