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
        if kinds.holds:
            self._hold(st, traffic)
        if kinds.walks:
            self._walk(st, traffic, uniforms[..., U_CHANGE])
        movers = traffic & (uniforms[..., U_RANDOM_LANE] < kinds.random_lane_prob[st.kind])
        # Ho's lane switcher tries only while slower than its own speed.
        return movers & (~kinds.random_lane_when_slow[st.kind] | (st.speed_mps < st.own_speed_mps))

    def _hold(self, st: SimState, traffic: np.ndarray) -> None:
        """The holding behaviours' desired speeds become the speeds they have, within their
        own speed and the top of their range (a car the car ahead slowed keeps its pace)."""
        kinds, kind = self.kinds, st.kind
        held = np.minimum(np.maximum(st.speed_mps, st.own_speed_mps), kinds.walk_hi[kind])
        st.desired_speed_mps[:] = np.where(
            traffic & kinds.keeps_current[kind], held, st.desired_speed_mps
        )

    def _walk(self, st: SimState, traffic: np.ndarray, uniform: np.ndarray) -> None:
        """One decision's step of the walking behaviours' desired speeds (``uniform`` (A, V):
        below P(up) a step up, then for P(down) a step down), kept within the walk's bounds
        (from the car's own speed where the behaviour names none)."""
        kinds, kind = self.kinds, st.kind
        up = kinds.walk_up[kind]
        down = kinds.walk_down[kind]
        step = kinds.walk_step[kind] * (
            (uniform < up).astype(np.float64) - ((uniform >= up) & (uniform < up + down))
        )
        lo = kinds.walk_lo[kind]
        lo = np.where(lo < 0.0, st.own_speed_mps, lo)
        walked = np.minimum(np.maximum(st.desired_speed_mps + step, lo), kinds.walk_hi[kind])
        st.desired_speed_mps[:] = np.where(
            traffic & (kinds.walk_step[kind] > 0), walked, st.desired_speed_mps
        )
