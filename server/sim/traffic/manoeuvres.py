"""Random manoeuvres of traffic: now and then a driver picks a new desired speed, or changes
lanes for no reason.

Min et al.'s traffic accelerates, decelerates and changes lanes at random (§IV.A). Here each
traffic car, per decision, picks a new desired speed within its behaviour's range with the
behaviour's chance (``speed_change_rate_per_s``), and its IDM then speeds up or slows down to
it; and with ``random_lane_change_rate_per_s`` it wants a lane change this decision whatever
MOBIL's incentive says, which MOBIL then makes only if its safety criterion holds (so that
traffic avoids colliding "in most cases"). A steady driver (both rates 0) does neither.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from overtake.protocol.vocabulary import AGENT_KIND

from ..randomness import U_CHANGE, U_NEW_SPEED, U_RANDOM_LANE

if TYPE_CHECKING:
    from ..state import SimState
    from ..vehicles import VehicleKinds


class RandomManoeuvres:
    """Per decision: new desired speeds, and the cars that want a lane change for no reason."""

    def __init__(self, kinds: VehicleKinds) -> None:
        self.kinds = kinds

    def decide(self, st: SimState, uniforms: np.ndarray) -> np.ndarray:
        """Apply new desired speeds; return (A, V) bool: the traffic cars that try a lane
        change this decision regardless of MOBIL's incentive."""
        kinds = self.kinds
        traffic = (st.kind < AGENT_KIND) & st.active
        change = traffic & (uniforms[..., U_CHANGE] < kinds.change_prob[st.kind])
        if change.any():
            new_speed = kinds.desired_speed(st.kind, uniforms[..., U_NEW_SPEED])
            st.desired_speed_mps[:] = np.where(change, new_speed, st.desired_speed_mps)
        return traffic & (uniforms[..., U_RANDOM_LANE] < kinds.random_lane_prob[st.kind])
