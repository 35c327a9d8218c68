"""Random manoeuvres of traffic: now and then a driver picks a new desired speed.

Min et al.'s traffic accelerates and brakes at random (§IV.A); here each traffic car, per
decision, picks a new desired speed within its behaviour's range with the behaviour's chance
(``speed_change_rate_per_s``), and its IDM then speeds up or slows down to it. A steady driver
(rate 0) never does.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from overtake.protocol.vocabulary import AGENT_KIND

from ..randomness import U_CHANGE, U_NEW_SPEED

if TYPE_CHECKING:
    from ..state import SimState
    from ..vehicles import VehicleKinds


class SpeedChanges:
    """Per decision, new desired speeds for the traffic cars whose draw says so."""

    def __init__(self, kinds: VehicleKinds) -> None:
        self.kinds = kinds

    def decide(self, st: SimState, uniforms: np.ndarray) -> None:
        kinds = self.kinds
        change = (
            (st.kind < AGENT_KIND)
            & st.active
            & (uniforms[..., U_CHANGE] < kinds.change_prob[st.kind])
        )
        if change.any():
            new_speed = kinds.desired_speed(st.kind, uniforms[..., U_NEW_SPEED])
            st.desired_speed_mps[:] = np.where(change, new_speed, st.desired_speed_mps)
