"""Traffic's treadmill in one compiled loop (numba): :meth:`.spawning.Spawner.recycle`'s
arithmetic, arena by arena and slot by slot, in the same float operations and order as the
numpy it replaced (the golden digests were not recorded again for it). Compiled and cached as
:mod:`.kernels` says.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from .traffic.kernels import desired_gap


@njit(cache=True, nogil=True, inline="always")
def drawn_anchor(active: np.ndarray, a: int, agents: int, uniform: float) -> int:
    """The agent of arena ``a`` a new car is placed by, picked by ``uniform`` in [0, 1): one
    off the road (a shared arena's free slot) is replaced by the first agent on it, unless
    none is on."""
    anchor = min(int(uniform * agents), agents - 1)
    if active[a, anchor]:
        return anchor
    for i in range(agents):
        if active[a, i]:
            return i
    return anchor


@njit(cache=True, nogil=True, inline="always")
def behaviour_of(behaviour_cdf: np.ndarray, uniform: float) -> int:
    """The traffic behaviour ``uniform`` picks by the behaviours' shares: numpy's
    ``searchsorted(cdf, uniform, side="right")``, capped at the last (as
    :meth:`.vehicles.VehicleKinds.behaviour_of`)."""
    behaviours = behaviour_cdf.size
    k = 0
    while k < behaviours and behaviour_cdf[k] <= uniform:
        k += 1
    return min(k, behaviours - 1)


@njit(cache=True, nogil=True, inline="always")
def put_car(
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
    a: int,
    c: int,
    at_x: float,
    at_lane: int,
    lane_centre_y: np.ndarray,
    at_speed: float,
    at_desired: float,
    at_own: float,
    at_kind: int,
) -> None:
    """A new car in slot ``c`` of arena ``a``: on the centre of its lane, not changing lanes,
    at ``at_speed``, wanting ``at_desired``, its behaviour's own speed ``at_own``."""
    x[a, c] = at_x
    lane[a, c] = target_lane[a, c] = at_lane
    change_progress[a, c] = 0.0
    y[a, c] = lane_centre_y[at_lane]
    speed[a, c] = at_speed
    desired_speed[a, c] = at_desired
    own_speed[a, c] = at_own
    accel[a, c] = 0.0
    kind[a, c] = at_kind
    active[a, c] = True


@njit(cache=True, nogil=True)
def kept_in_range(
    x: np.ndarray,
    active: np.ndarray,
    agents: int,
    keep_ahead_m: float,
    keep_behind_m: float,
    kept: np.ndarray,
) -> None:
    """Per traffic slot (A, T): whether it is within ``keep_ahead_m`` / ``keep_behind_m`` of
    some anchoring agent. Agents off the road (a shared arena's free slots) anchor nothing,
    unless none is on."""
    arenas, vehicles = x.shape
    for a in range(arenas):
        any_present = False
        for i in range(agents):
            any_present = any_present or active[a, i]
        for t in range(vehicles - agents):
            c = agents + t
            inside = False
            for i in range(agents):
                anchor = active[a, i] or not any_present
                dx = x[a, c] - x[a, i]
                if anchor and dx <= keep_ahead_m and dx >= -keep_behind_m:
                    inside = True
                    break
            kept[a, t] = inside


@njit(cache=True, nogil=True)
def respawn(
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
    keep_ahead_m: float,
    keep_behind_m: float,
    uniforms: np.ndarray,
    u_side: int,
    u_anchor: int,
    u_lane: int,
    u_offset: int,
    u_behaviour: int,
    u_speed: int,
    ahead_windows: np.ndarray,
    behind_windows: np.ndarray,
    lane_centre_y: np.ndarray,
    behaviour_cdf: np.ndarray,
    speed_lo: np.ndarray,
    speed_hi: np.ndarray,
    half_length: np.ndarray,
    headway: np.ndarray,
    min_gap: np.ndarray,
    two_sqrt_ab: np.ndarray,
    enter_at_leader_speed: bool,
    separation_m: float,
    spawned: np.ndarray,
) -> int:
    """Respawn every traffic car out of every agent's range and fill the empty slots, in place
    on the (A, V) state arrays; marks the slots that got a car in ``spawned`` (A, V) and returns
    how many did.

    A slot to fill draws its anchoring agent, its side (ahead of or behind it), its behaviour
    and desired speed, and ``ahead_windows`` / ``behind_windows`` (2, M)'s M candidate spots
    (lane and distance) from its row of ``uniforms`` (A, V, U) at the ``u_*`` columns; it
    takes the first candidate that keeps an IDM-comfortable gap to every vehicle sharing its
    lane (at its leader's speed where that is slower, with ``enter_at_leader_speed``), unless
    an earlier slot of the arena found a spot in the same lane within ``separation_m``: then
    it waits a decision, as does a slot with no free candidate. The per-kind tables are
    indexed by ``kind``."""
    arenas, vehicles = x.shape
    traffic = vehicles - agents
    candidates = ahead_windows.shape[1]
    lanes = lane_centre_y.size
    kept = np.empty((arenas, traffic), dtype=np.bool_)
    kept_in_range(x, active, agents, keep_ahead_m, keep_behind_m, kept)
    # Per slot of an arena: the spot found, if any.
    found = np.zeros(traffic, dtype=np.bool_)
    pick_lane = np.zeros(traffic, dtype=np.int64)
    pick_x = np.zeros(traffic)
    pick_speed = np.zeros(traffic)
    new_kind = np.zeros(traffic, dtype=np.int64)
    new_desired = np.zeros(traffic)
    need = np.zeros(traffic, dtype=np.bool_)
    total = 0
    for a in range(arenas):
        # Out-of-range cars move at once; empty slots (no free spot found yet) try again
        # every decision, so that the road holds its density. All of them leave the road
        # before any spot is sought.
        needed = 0
        for t in range(traffic):
            c = agents + t
            need[t] = not active[a, c] or not kept[a, t]
            found[t] = False
            if need[t]:
                active[a, c] = False
                needed += 1
        if needed == 0:
            continue
        for t in range(traffic):
            if not need[t]:
                continue
            u = uniforms[a, agents + t]
            # The side is drawn, for a car out of range as for an empty slot. (The numpy code
            # this replaced meant to bring a car left behind back ahead, and one left ahead
            # back behind; but it read that from a view of ``active`` it had just cleared, so
            # every side was drawn. The kept tables were made so; this keeps it.)
            ahead_side = u[u_side] < 0.5
            anchor = drawn_anchor(active, a, agents, u[u_anchor])
            windows = ahead_windows if ahead_side else behind_windows
            k = behaviour_of(behaviour_cdf, u[u_behaviour])
            desired = speed_lo[k] + u[u_speed] * (speed_hi[k] - speed_lo[k])
            new_kind[t] = k
            new_desired[t] = desired
            for m in range(candidates):
                c_lane = min(int(u[u_lane + m] * lanes), lanes - 1)
                distance = windows[0, m] + u[u_offset + m] * (windows[1, m] - windows[0, m])
                c_x = x[a, anchor] + (distance if ahead_side else -distance)
                c_speed = desired
                if enter_at_leader_speed:
                    nearest = np.inf
                    leader = 0
                    for o in range(vehicles):
                        if not active[a, o]:
                            continue
                        if lane[a, o] != c_lane and target_lane[a, o] != c_lane:
                            continue
                        if x[a, o] >= c_x and x[a, o] - c_x < nearest:
                            nearest = x[a, o] - c_x
                            leader = o
                    if nearest < np.inf:
                        c_speed = min(c_speed, speed[a, leader])
                clear = True
                for o in range(vehicles):
                    if not active[a, o]:
                        continue
                    if lane[a, o] != c_lane and target_lane[a, o] != c_lane:
                        continue
                    ok_ = kind[a, o]
                    dx = x[a, o] - c_x
                    bodies = half_length[ok_] + half_length[k]
                    if dx >= 0.0:
                        need_ahead = desired_gap(
                            c_speed, c_speed - speed[a, o], headway[k], min_gap[k], two_sqrt_ab[k]
                        )
                        clear = dx - bodies >= need_ahead
                    else:
                        need_behind = desired_gap(
                            speed[a, o],
                            speed[a, o] - c_speed,
                            headway[ok_],
                            min_gap[ok_],
                            two_sqrt_ab[ok_],
                        )
                        clear = -dx - bodies >= need_behind
                    if not clear:
                        break
                if clear:
                    found[t] = True
                    pick_lane[t], pick_x[t], pick_speed[t] = c_lane, c_x, c_speed
                    break
        # Two spawns of this decision may not land on each other: the later one waits (an
        # earlier spot counts even where it waits itself).
        for t in range(traffic - 1, -1, -1):
            if not found[t]:
                continue
            for s in range(t):
                if (
                    found[s]
                    and pick_lane[s] == pick_lane[t]
                    and abs(pick_x[t] - pick_x[s]) < separation_m
                ):
                    found[t] = False
                    break
        for t in range(traffic):
            if not found[t]:
                continue
            c = agents + t
            put_car(
                x, lane, target_lane, change_progress, y, speed, desired_speed, own_speed,
                accel, kind, active, a, c, pick_x[t], pick_lane[t], lane_centre_y,
                pick_speed[t], new_desired[t], new_desired[t], new_kind[t],
            )  # fmt: skip
            spawned[a, c] = True
            total += 1
    return total
