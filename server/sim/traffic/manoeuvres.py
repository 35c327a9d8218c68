"""Random manoeuvres of traffic: now and then a driver picks a new desired speed or steps it
up or down, or changes lanes for no reason.

Min et al.'s traffic accelerates, decelerates and changes lanes at random (§IV.A). Here each
traffic car, per decision, picks a new desired speed within its behaviour's range with the
behaviour's chance (``speed_change_rate_per_s``), and its IDM then speeds up or slows down to
it; and with ``random_lane_change_rate_per_s`` it wants a lane change this decision whatever
MOBIL's incentive says, which MOBIL then makes only if its safety criterion holds (so that
traffic avoids colliding "in most cases"). A behaviour with a speed walk
(``speed_steps_per_s``) instead steps its desired speed up or down, one draw a decision
(:func:`..vehicles.speed_walk_per_decision`): Min et al.'s code steps 5 km/h every 5 s, up
three times in four, within 40-80 km/h; Ho's "stick to max" cars wander between their own
speed and 100 km/h. A steady driver (every rate 0) does none of these.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from overtake.protocol.vocabulary import AGENT_KIND

from ..randomness import U_CHANGE, U_NEW_SPEED, U_RANDOM_LANE
from . import kernels

if TYPE_CHECKING:
    from ..state import SimState
    from ..vehicles import VehicleKinds


class RandomManoeuvres:
    """Per decision: new desired speeds, and the cars that want a lane change for no reason."""

    def __init__(self, kinds: VehicleKinds) -> None:
        self.kinds = kinds

    def decide(self, st: SimState, uniforms: np.ndarray) -> np.ndarray:
        """Apply new desired speeds; return (A, V) bool: the traffic cars that try a lane
        change this decision regardless of MOBIL's incentive. One compiled loop
        (:func:`.kernels.random_manoeuvres`): a new desired speed with the behaviour's chance,
        then a holding behaviour's pace (its speed, within its own speed and the top of its
        range: a car the car ahead slowed keeps its pace), then a walking behaviour's step
        (below P(up) a step up, then for P(down) a step down, within the walk's bounds, from
        the car's own speed where the behaviour names none)."""
        k = self.kinds
        movers = np.empty(st.kind.shape, dtype=bool)
        kernels.random_manoeuvres(
            st.kind, st.active, st.speed_mps, st.own_speed_mps, st.desired_speed_mps, uniforms,
            U_CHANGE, U_NEW_SPEED, U_RANDOM_LANE, AGENT_KIND, k.change_prob, k.speed_lo,
            k.speed_hi, k.keeps_current, k.walk_step, k.walk_up, k.walk_down, k.walk_lo,
            k.walk_hi, k.random_lane_prob, k.random_lane_when_slow, movers,
        )  # fmt: skip
        return movers
