"""Who passed whom: each agent's overtakes, and the cars that pass it.

A pass is a car's centre moving from ahead of the agent's centre to behind it (an overtake by
the agent) or the other way (the agent being passed), between two decisions. An overtake counts
once per car: a car the agent passes, falls behind and passes again is not counted twice,
unless ``reward.undo_overtake_when_passed_back`` takes the overtake back when that car passes
the agent; with ``reward.overtakes_counted = "every_pass"`` (Ho) every crossing counts. A
vehicle that just appeared (spawned, recycled, respawned) starts its tracking afresh, so an
appearance is never a pass.
"""

from __future__ import annotations

import numpy as np

from .state import SimState


class OvertakeTracker:
    """Overtake bookkeeping (``ahead`` and ``credited`` of the state) for every agent."""

    def __init__(
        self, agents: int, vehicles: int, undo_when_passed_back: bool, every_pass: bool = False
    ) -> None:
        self.agents = agents
        self.undo_when_passed_back = undo_when_passed_back
        self.every_pass = every_pass
        # (1, N, V): False where an agent would be compared with itself.
        self._not_self = np.ones((1, agents, vehicles), dtype=bool)
        self._not_self[0, np.arange(agents), np.arange(agents)] = False

    def start(self, st: SimState, vehicles: np.ndarray) -> None:
        """Reset the tracking of the (A, V) ``vehicles`` that just appeared."""
        ahead_now = st.x_m[:, None, :] > st.x_m[:, : self.agents, None]
        mask = vehicles[:, None, :]
        st.ahead[:] = np.where(mask, ahead_now, st.ahead)
        st.credited[:] = st.credited & ~mask

    def start_agent(self, st: SimState, arena: int, slot: int) -> None:
        """Restart an agent's tracking both ways: what it has ahead of it, and whether it is
        ahead of each other agent."""
        n = self.agents
        st.ahead[arena, slot] = st.x_m[arena] > st.x_m[arena, slot]
        st.credited[arena, slot] = False
        st.ahead[arena, :n, slot] = st.x_m[arena, slot] > st.x_m[arena, :n]
        st.credited[arena, :n, slot] = False

    def track(self, st: SimState) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(A, N) each: cars the agent passed (the first time, or every time with
        ``every_pass``), overtakes undone, cars passing it."""
        n = self.agents
        ahead_now = st.x_m[:, None, :] > st.x_m[:, :n, None]
        live = st.active[:, None, :] & self._not_self
        overtook = st.ahead & ~ahead_now & live
        got_passed = ~st.ahead & ahead_now & live
        gained = (overtook if self.every_pass else overtook & ~st.credited).sum(axis=-1)
        st.credited |= overtook
        passed = got_passed.sum(axis=-1)
        undone = np.zeros_like(gained)
        if self.undo_when_passed_back:
            taken_back = got_passed & st.credited
            undone = taken_back.sum(axis=-1)
            st.credited &= ~taken_back
        st.ahead[:] = ahead_now
        return gained, undone, passed
