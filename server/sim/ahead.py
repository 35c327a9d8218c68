"""Each agent's car ahead: what the forward warning (:class:`.assist.DriverWarnings`), the
sensors' ego vector and the lane-change watch's fail-safe brake (:mod:`.lane_watch`) all
read."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from . import kernels

if TYPE_CHECKING:
    from .state import SimState
    from .vehicles import VehicleKinds


@dataclass(slots=True)
class CarsAhead:
    """Each agent's car ahead, (A, N): the nearest vehicle in front in a lane the agent is in
    or moving into (or moving into the agent's), bumper to bumper."""

    gap_m: np.ndarray  # inf where there is none
    speed_mps: np.ndarray  # the agent's own speed where there is none
    present: np.ndarray  # bool


def cars_ahead(st: SimState, kinds: VehicleKinds, agents: int) -> CarsAhead:
    """The car ahead of each of the first ``agents`` vehicles of every arena, in a compiled
    loop (:func:`.kernels.cars_ahead`)."""
    shape = (st.x_m.shape[0], agents)
    gap_m, speed_mps = np.empty(shape), np.empty(shape)
    kernels.cars_ahead(
        st.x_m,
        st.speed_mps,
        st.lane,
        st.target_lane,
        st.active,
        kinds.half_length[st.kind],
        agents,
        gap_m,
        speed_mps,
    )
    return CarsAhead(gap_m=gap_m, speed_mps=speed_mps, present=np.isfinite(gap_m))
