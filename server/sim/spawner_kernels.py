"""Min et al.'s spawners in one compiled loop (numba): :meth:`.spawners.Spawners.step`'s
arithmetic, arena by arena: the cars that leave the road, then each spawner's try. Compiled
and cached as :mod:`.kernels` says.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .spawning_kernels import behaviour_of, drawn_anchor, put_car


@njit(cache=True, nogil=True, inline="always")
def attempt_interval_s(interval_cdf: np.ndarray, step_s: float, uniform: float) -> float:
    """The time until a spawner's next try that ``uniform`` in [0, 1) picks: ``interval_cdf``
    [k] is the chance that it comes within k + 1 fixed steps of ``step_s``."""
    index = int(np.searchsorted(interval_cdf, uniform, side="right"))
    return (min(index, interval_cdf.size - 1) + 1) * step_s


@njit(cache=True, nogil=True)
def leave_and_spawn(
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
    spawner_wait_s: np.ndarray,
    agents: int,
    keep_ahead_m: float,
    keep_behind_m: float,
    half_length: np.ndarray,
    half_width: np.ndarray,
    uniforms: np.ndarray,
    u_side: int,
    u_anchor: int,
    u_lane: int,
    u_offset: int,
    u_behaviour: int,
    u_speed: int,
    u_wait: int,
    decision_period_s: float,
    spawner_first: np.ndarray,
    spawner_slots: np.ndarray,
    interval_cdf: np.ndarray,
    step_s: float,
    ahead_share: float,
    ahead_window_m: np.ndarray,
    behind_window_m: np.ndarray,
    clearance_m: float,
    clearance_across_m: float,
    lane_centre_y: np.ndarray,
    behaviour_cdf: np.ndarray,
    speed_lo: np.ndarray,
    speed_hi: np.ndarray,
    spawned: np.ndarray,
) -> int:
    """One decision of the spawners of every arena, in place on the (A, V) state arrays and
    ``spawner_wait_s`` (A, S); marks the slots that got a new car in ``spawned`` (A, V) and
    returns how many did.

    First the cars leave: a traffic car further than ``keep_ahead_m`` (ahead) or
    ``keep_behind_m`` (behind) in a straight line from every agent on the road (every agent
    where none is on), and every traffic car whose box overlaps another's (both go). Then
    each spawner s with slots (``spawner_slots[s]`` of them, from traffic slot
    ``spawner_first[s]``) runs its clock down by ``decision_period_s``; where it has run out
    it tries once and draws its next wait from ``interval_cdf``. A try reads its draws from
    the row of ``uniforms`` (A, V, U) of the spawner's first slot (columns ``u_*``): the
    side (ahead with ``ahead_share``), the agent it places by, the lane (even), the distance
    in the side's window (whole metres from its first up to its second), the behaviour and
    desired speed of the car, and the wait. The car goes into the spawner's first free slot,
    at its desired speed, unless the spawner's slots are full or some vehicle's centre is
    within ``clearance_m`` along the road and ``clearance_across_m`` across of the spot.
    Spawners try in order, each seeing the cars the ones before it placed."""
    arenas, vehicles = x.shape
    traffic = vehicles - agents
    lanes = lane_centre_y.size
    spawners = spawner_slots.size
    touched = np.zeros(traffic, dtype=np.bool_)
    total = 0
    for a in range(arenas):
        any_present = False
        for i in range(agents):
            any_present = any_present or active[a, i]
        # Out of range, in a straight line from the host (TargetManagement.cs).
        for t in range(traffic):
            c = agents + t
            if not active[a, c]:
                continue
            inside = False
            for i in range(agents):
                if not (active[a, i] or not any_present):
                    continue
                dx = x[a, c] - x[a, i]
                dy = y[a, c] - y[a, i]
                reach = keep_ahead_m if dx >= 0.0 else keep_behind_m
                if dx * dx + dy * dy <= reach * reach:
                    inside = True
                    break
            if not inside:
                active[a, c] = False
        # Cars that touch destroy themselves, both of them (their trigger boxes).
        for t in range(traffic):
            touched[t] = False
        for t in range(traffic):
            c = agents + t
            if not active[a, c]:
                continue
            for s in range(t + 1, traffic):
                d = agents + s
                if not active[a, d]:
                    continue
                if abs(x[a, c] - x[a, d]) < half_length[kind[a, c]] + half_length[kind[a, d]] and (
                    abs(y[a, c] - y[a, d]) < half_width[kind[a, c]] + half_width[kind[a, d]]
                ):
                    touched[t] = True
                    touched[s] = True
        for t in range(traffic):
            if touched[t]:
                active[a, agents + t] = False
        # The spawners' tries.
        for s in range(spawners):
            if spawner_slots[s] == 0:
                continue
            spawner_wait_s[a, s] -= decision_period_s
            if spawner_wait_s[a, s] > 0.0:
                continue
            u = uniforms[a, agents + spawner_first[s]]
            spawner_wait_s[a, s] += attempt_interval_s(interval_cdf, step_s, u[u_wait])
            slot = -1
            for t in range(spawner_first[s], spawner_first[s] + spawner_slots[s]):
                if not active[a, agents + t]:
                    slot = agents + t
                    break
            if slot < 0:
                continue
            ahead_side = u[u_side] < ahead_share
            window = ahead_window_m if ahead_side else behind_window_m
            distance = window[0] + math.floor(u[u_offset] * (window[1] - window[0]))
            anchor = drawn_anchor(active, a, agents, u[u_anchor])
            at_x = x[a, anchor] + (distance if ahead_side else -distance)
            at_lane = min(int(u[u_lane] * lanes), lanes - 1)
            at_y = lane_centre_y[at_lane]
            clear = True
            for o in range(vehicles):
                if (
                    active[a, o]
                    and abs(x[a, o] - at_x) < clearance_m
                    and abs(y[a, o] - at_y) < clearance_across_m
                ):
                    clear = False
                    break
            if not clear:
                continue
            k = behaviour_of(behaviour_cdf, u[u_behaviour])
            desired = speed_lo[k] + u[u_speed] * (speed_hi[k] - speed_lo[k])
            put_car(
                x, lane, target_lane, change_progress, y, speed, desired_speed, own_speed,
                accel, kind, active, a, slot, at_x, at_lane, lane_centre_y, desired, desired,
                desired, k,
            )  # fmt: skip
            spawned[a, slot] = True
            total += 1
    return total
