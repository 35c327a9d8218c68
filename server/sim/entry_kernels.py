"""Ho's entry rule in one compiled loop (numba): :meth:`.entry.FreeZoneEntry.enter`'s
arithmetic, arena by arena and try by try, in the same float operations and order as the numpy
it replaced (the golden digests were not recorded again for it). Compiled and cached as
:mod:`.kernels` says.
"""

from __future__ import annotations

import numpy as np
from numba import njit


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
    behaviours = behaviour_cdf.size
    occupied = np.zeros(lanes, dtype=np.bool_)
    total = 0
    for a in range(arenas):
        # Agents off the road (a shared arena's free slots) anchor nothing, unless none is on.
        any_present = False
        first_anchor = 0
        for i in range(agents):
            if active[a, i] and not any_present:
                first_anchor = i
            any_present = any_present or active[a, i]
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
            anchor = min(int(draws[3] * agents), agents - 1)
            if not (active[a, anchor] or not any_present):
                anchor = first_anchor
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
            # The behaviour a uniform picks by the shares (searchsorted, side right).
            b = 0
            while b < behaviours and behaviour_cdf[b] <= own[u_behaviour]:
                b += 1
            b = min(b, behaviours - 1)
            own_mps = speed_lo[b] + own[u_speed] * (speed_hi[b] - speed_lo[b])
            low, high = entry_speed_mps[side, 0], entry_speed_mps[side, 1]
            entry_mps = low + own[u_offset] * (high - low)
            x[a, slot] = point
            lane[a, slot] = target_lane[a, slot] = new_lane
            y[a, slot] = lane_centre_y[new_lane]
            change_progress[a, slot] = 0.0
            speed[a, slot] = entry_mps
            own_speed[a, slot] = own_mps
            desired_speed[a, slot] = max(own_mps, entry_mps)
            accel[a, slot] = 0.0
            kind[a, slot] = b
            active[a, slot] = True
            entered[a, slot] = True
            total += 1
    return total
