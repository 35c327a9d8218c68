"""Driver assistance that watches a lane change through (``ego.lane_change_watch``, issue 46).

A lane change judged safe when it starts can turn unsafe while the car moves across: a car two
lanes over starts into the same lane, a fast car closes in behind, the new lane's leader brakes.
Every published zero-collision highway result checks the change through the manoeuvre
(highway-env's traffic retargets its own lane when another car targets the same gap; UN R79 and
R157 ask a stalled change to complete or return; Mirchevska et al. 2018 and Krasowski et al.
2020 verify it against traffic that moves meanwhile). This is that check, in the car: the
shield's option (``--shield`` turns it on), off in the papers' presets, whose code has none.

The rule, fixed before any run that measures it and not tuned on their results:

- **Safe** (the same at the start and in every physics frame of a change): for every other car
  in the target lane or moving into it, the follower of the two (the agent behind a car ahead,
  a car behind the agent), reacting after ``ego.watch_response_s`` (0.4 s) and braking at
  ``ego.watch_brake_mps2`` (3 m/s^2: the response time and the deceleration UN R79 allows a
  lane change to ask of the traffic it joins), stops closing in before the gap, bumper to
  bumper, falls under ``ego.min_gap_m``. A car alongside is never safe.
- **Start**: a change the rule finds unsafe does not start (the car keeps its lane; the action
  applied is keep).
- **Abort**: a change found unsafe before the car's centre reaches the lane marking (half way:
  the minimum-jerk move is symmetric) turns back: the car steers back to its lane along the
  path it came, for as long as it had moved; an episode counts these (``lane_change_aborts``).
- **Fail-safe**: past the marking the change completes; and in every frame where stopping the
  closing in on its nearest car ahead (in its lane or the one it moves into, or moving into
  either: a car cutting in is met by the same brake) before the gap falls under
  ``ego.min_gap_m`` takes more than comfortable braking (``ego.comfort_decel_mps2``, where
  cruise control stops), the car brakes as hard as that takes, up to ``ego.aeb_decel_mps2``
  (emergency braking waits for a time to collision of 1.5 s). Below it, driving is as without
  the watch.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from . import kernels
from .ahead import cars_ahead

if TYPE_CHECKING:
    from .assist import EgoConfig
    from .state import SimState
    from .vehicles import VehicleKinds

# The progress through a change at which the car's centre is on the lane marking: the
# minimum-jerk move is half done at half time. Before it a change can turn back.
NO_RETURN_PROGRESS = 0.5
# Where the room left to the car ahead is this small (m) or less, the fail-safe brakes fully.
_NO_ROOM_M = 0.05


class LaneChangeWatch:
    """The rule of the module's docstring, for ``agents`` agents."""

    def __init__(self, ego: EgoConfig, kinds: VehicleKinds, agents: int) -> None:
        self.response_s = ego.watch_response_s
        self.brake_mps2 = ego.watch_brake_mps2
        self.min_gap_m = ego.min_gap_m
        self.full_brake_mps2 = ego.aeb_decel_mps2
        self.comfort_mps2 = ego.comfort_decel_mps2
        self.kinds = kinds
        self.agents = agents

    def unsafe(self, st: SimState) -> np.ndarray:
        """(A, N) bool: the agents changing lanes whose target lane is not safe now."""
        out = np.empty((st.x_m.shape[0], self.agents), dtype=bool)
        kernels.unsafe_changes(
            st.x_m,
            st.speed_mps,
            self.kinds.half_length[st.kind],
            st.active,
            st.lane,
            st.target_lane,
            self.agents,
            self.response_s,
            self.brake_mps2,
            self.min_gap_m,
            out,
        )
        return out

    def refuse_unsafe_starts(self, st: SimState, started: np.ndarray) -> np.ndarray:
        """Undo the changes just started (``started`` (A, N), their targets set) that the rule
        finds unsafe; returns those that stand."""
        unsafe = self.unsafe(st) & started
        if unsafe.any():
            n = self.agents
            st.target_lane[:, :n] = np.where(unsafe, st.lane[:, :n], st.target_lane[:, :n])
        return started & ~unsafe

    def frame(self, st: SimState, accel: np.ndarray) -> None:
        """One physics frame, before the cars move: turn back the unsafe changes that still
        can (counted in ``st.lane_change_aborts``), and lower each agent's acceleration in
        ``accel`` (A, V) to the fail-safe brake its car ahead needs."""
        n = self.agents
        if (st.target_lane[:, :n] != st.lane[:, :n]).any():
            progress = st.change_progress[:, :n]
            back = self.unsafe(st) & (progress < NO_RETURN_PROGRESS)
            if back.any():
                # The same path backwards: from the target lane to the origin, as far through
                # as the car had yet to go (the minimum-jerk profile is symmetric).
                origin = st.lane[:, :n].copy()
                st.lane[:, :n] = np.where(back, st.target_lane[:, :n], origin)
                st.target_lane[:, :n] = np.where(back, origin, st.target_lane[:, :n])
                st.change_progress[:, :n] = np.where(back, 1.0 - progress, progress)
                st.lane_change_aborts += back
        ahead = cars_ahead(st, self.kinds, n)
        gap_m, speed_ahead = ahead.gap_m, ahead.speed_mps
        closing = st.speed_mps[:, :n] - speed_ahead
        if not (closing > 0.0).any():
            return
        room = gap_m - self.min_gap_m
        with np.errstate(divide="ignore", invalid="ignore"):  # no car ahead: infinite gap
            needed = np.where(
                room > _NO_ROOM_M,
                closing * closing / (2.0 * np.maximum(room, _NO_ROOM_M)),
                self.full_brake_mps2,
            )
        # Only where cruise control's comfortable braking would not do.
        critical = (closing > 0.0) & (needed > self.comfort_mps2)
        if not critical.any():
            return
        # Lowered where critical only: elsewhere the acceleration stays what it was.
        braked = np.minimum(accel[:, :n], -np.minimum(needed, self.full_brake_mps2))
        accel[:, :n] = np.where(critical, braked, accel[:, :n])
