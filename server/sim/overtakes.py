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

from .kernels import track_passes
from .state import SimState


class OvertakeTracker:
    """Overtake bookkeeping (``ahead`` and ``credited`` of the state) for every agent."""

    def __init__(
        self, agents: int, vehicles: int, undo_when_passed_back: bool, every_pass: bool = False
    ) -> None:
        self.agents = agents
        self.undo_when_passed_back = undo_when_passed_back
        self.every_pass = every_pass

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

    def track(
        self, st: SimState, stepped: np.ndarray | None = None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(A, N) each: cars the agent passed (the first time, or every time with
        ``every_pass``), overtakes undone, cars passing it; in the arenas ``stepped`` (A,)
        bool (None: all), 0 in the others, whose tracking is left as it was."""
        shape = st.distance_m.shape
        gained, undone, passed = (np.zeros(shape, dtype=np.int64) for _ in range(3))
        if stepped is None:
            stepped = np.ones(shape[0], dtype=bool)
        track_passes(
            st.x_m, st.active, st.ahead, st.credited, self.every_pass,
            self.undo_when_passed_back, stepped, gained, undone, passed,
        )  # fmt: skip
        return gained, undone, passed
