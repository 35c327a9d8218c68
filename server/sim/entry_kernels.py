"""Ho's entry rule in one compiled loop (numba): :meth:`.entry.FreeZoneEntry.enter`'s
arithmetic, arena by arena and try by try, in the same float operations and order as the numpy
it replaced (the golden digests were not recorded again for it). Compiled and cached as
:mod:`.kernels` says.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .spawning_kernels import behaviour_of, drawn_anchor, put_car


@njit(cache=True, nogil=True)
def enter_free_zones(
    x: np.ndarray,
    lane: np.ndarray,
    target_lane: np.ndarray,
    change_progress: np.ndarray,
    y: np.ndarray,
    speed: np.ndarray,
    desired_speed: np.ndarray,
    own_speed: np.ndarray,
    accel: np.ndarray,
    kind: np.ndarray,
    active: np.ndarray,
    agents: int,
    uniforms: np.ndarray,
    tries: int,
    try_draws: int,
    prob: float,
    offset_m: np.ndarray,
    zone_m: np.ndarray,
    entry_speed_mps: np.ndarray,
    u_behaviour: int,
    u_speed: int,
    u_offset: int,
    lane_centre_y: np.ndarray,
    behaviour_cdf: np.ndarray,
    speed_lo: np.ndarray,
    speed_hi: np.ndarray,
    entered: np.ndarray,
) -> int:
    """Up to ``tries`` entries per arena into its free traffic slots, in place on the (A, V)
    state arrays; marks the slots entered in ``entered`` (A, V) and returns how many.

    Try k of an arena reads its draws from the first agent's row of ``uniforms`` (A, V, U),
    columns ``k * try_draws`` on: whether it happens (probability ``prob``, and only with a
    free slot), the side (0 ahead, 1 behind), the lane among the side's free ones, the agent.
    The entry point is ``offset_m[side]`` from that agent; a lane is free where no car is
    in or moving into ``zone_m[side]`` (2,) around it. The new car (the first free slot) takes
    its behaviour and own speed from its slot's row at ``u_behaviour`` / ``u_speed``, its
    entry speed within ``entry_speed_mps[side]`` at ``u_offset``."""
    arenas, vehicles = x.shape
    lanes = lane_centre_y.size
    occupied = np.zeros(lanes, dtype=np.bool_)
    total = 0
    for a in range(arenas):
        for attempt in range(tries):
            draws = uniforms[a, 0, attempt * try_draws : (attempt + 1) * try_draws]
            slot = -1
            for c in range(agents, vehicles):
                if not active[a, c]:
                    slot = c
                    break
            if not (draws[0] < prob and slot >= 0):
                continue
            side = 1 if draws[1] >= 0.5 else 0
            anchor = drawn_anchor(active, a, agents, draws[3])
            point = x[a, anchor] + offset_m[side]
            occupied[:] = False
            for v in range(vehicles):
                dx = x[a, v] - point
                if active[a, v] and dx >= zone_m[side, 0] and dx <= zone_m[side, 1]:
                    occupied[lane[a, v]] = True
                    occupied[target_lane[a, v]] = True
            count = 0
            for k in range(lanes):
                count += not occupied[k]
            if count == 0:
                continue
            pick = min(int(draws[2] * count), max(count - 1, 0))
            new_lane = 0
            seen = 0
            for k in range(lanes):
                if not occupied[k]:
                    if seen == pick:
                        new_lane = k
                        break
                    seen += 1
            own = uniforms[a, slot]
            b = behaviour_of(behaviour_cdf, own[u_behaviour])
            own_mps = speed_lo[b] + own[u_speed] * (speed_hi[b] - speed_lo[b])
            low, high = entry_speed_mps[side, 0], entry_speed_mps[side, 1]
            entry_mps = low + own[u_offset] * (high - low)
            put_car(
                x, lane, target_lane, change_progress, y, speed, desired_speed, own_speed,
                accel, kind, active, a, slot, point, new_lane, lane_centre_y, entry_mps,
                max(own_mps, entry_mps), own_mps, b,
            )  # fmt: skip
            entered[a, slot] = True
            total += 1
    return total
