"""The physics frame's and driver assistance's compiled loops (numba): the minimum-jerk lateral
profile, moving every vehicle by a frame, the agents' collisions, each agent's car ahead, and
the side check before a lane change. The sensors' loops are in :mod:`.sensors.kernels`,
car-following's in :mod:`.traffic.kernels`.

Compiled on first use and cached on disk (``cache=True``: next to this file, or under
``NUMBA_CACHE_DIR`` where that is not writable); ``python -m overtake.server.sim.warm``
compiles them ahead. They do the same float operations in the same order as the numpy code
they replaced (``tests/server/sim/test_golden.py`` was not re-recorded for them); with
``NUMBA_DISABLE_JIT=1`` they run as plain Python (slow, for debugging).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def min_jerk(progress: float) -> float:
    """Minimum-jerk lateral profile: 0 -> 1 with zero speed and acceleration at both ends."""
    p = min(max(progress, 0.0), 1.0)
    return p * p * p * (10.0 - 15.0 * p + 6.0 * p * p)


@njit(cache=True, nogil=True)
def integrate(
    speed: np.ndarray,
    new_speed: np.ndarray,
    active: np.ndarray,
    x_m: np.ndarray,
    accel_mps2: np.ndarray,
    distance_m: np.ndarray,
    lane: np.ndarray,
    target_lane: np.ndarray,
    change_progress: np.ndarray,
    change_rate: np.ndarray,
    y_m: np.ndarray,
    lane_width_m: float,
    dt: float,
) -> None:
    """Move every vehicle by one frame, in place: along the road at the mean of its old and
    new speeds (``speed`` becomes ``new_speed``, ``accel_mps2`` the frame's change, the agents'
    ``distance_m`` (A, N) grows), and sideways on its minimum-jerk lane change; a change that
    completes puts the car in its target lane. Where no vehicle of the batch changes lanes,
    nothing moves sideways."""
    arenas, vehicles = speed.shape
    agents = distance_m.shape[1]
    changing = False
    for a in range(arenas):
        for v in range(vehicles):
            old, new = speed[a, v], new_speed[a, v]
            travelled = 0.5 * (old + new) * dt if active[a, v] else 0.0
            accel_mps2[a, v] = (new - old) / dt
            x_m[a, v] += travelled
            speed[a, v] = new
            if v < agents:
                distance_m[a, v] += travelled
            if target_lane[a, v] != lane[a, v]:
                changing = True
    if not changing:
        return
    for a in range(arenas):
        for v in range(vehicles):
            target = target_lane[a, v]
            progress = 0.0
            if target != lane[a, v]:
                progress = change_progress[a, v] + change_rate[a, v]
            if progress >= 1.0:
                lane[a, v] = target
                progress = 0.0
            change_progress[a, v] = progress
            shift = (target - lane[a, v]) * min_jerk(progress)
            y_m[a, v] = (lane[a, v] + 0.5 + shift) * lane_width_m


@njit(cache=True, nogil=True)
def speed_steps(
    speed: np.ndarray,
    has_leader: np.ndarray,
    gap_m: np.ndarray,
    leader_speed: np.ndarray,
    command: np.ndarray,
    step_mps: float,
    min_mps: float,
    max_mps: float,
    safety_gap_m: float,
    more_than_mps: float,
    new_speed: np.ndarray,
    forced: np.ndarray,
) -> None:
    """Ho's speed steps for the agents (the first N columns of the (A, V) arrays): each one's
    speed moves by its ``command`` (A, N) (-1, 0, +1) steps within [min, max], but not up
    within ``safety_gap_m`` of a leader, where the safety rule takes a slower leader's speed
    at once; written to ``new_speed``'s agent columns. ``forced`` (A, N) marks the agents that
    rule sets to a leader slower by more than ``more_than_mps`` (his ``hard_brake_count``).
    The arithmetic of :class:`.assist.SpeedSteps`."""
    arenas, agents = command.shape
    for a in range(arenas):
        for i in range(agents):
            own = speed[a, i]
            lead = leader_speed[a, i]
            near = has_leader[a, i] and gap_m[a, i] < safety_gap_m
            step = command[a, i]
            if near and step > 0:
                step = 0
            new = min(max(own + step * step_mps, min_mps), max_mps)
            if near and lead < own:
                new = lead
            new_speed[a, i] = new
            forced[a, i] = near and own - lead > more_than_mps


@njit(cache=True, nogil=True)
def agent_overlaps(
    x_m: np.ndarray,
    y_m: np.ndarray,
    half_length_m: np.ndarray,
    half_width_m: np.ndarray,
    active: np.ndarray,
    agents: int,
    collided: np.ndarray,
) -> None:
    """Mark in ``collided`` (A, N) the agents whose box overlaps another active vehicle's
    (boxes aligned with the road: |dx| below the half lengths' sum and |dy| below the half
    widths'), arena by arena; an agent's own slot does not count."""
    arenas, vehicles = x_m.shape
    for a in range(arenas):
        for i in range(agents):
            if not active[a, i]:
                continue
            for v in range(vehicles):
                if v == i or not active[a, v]:
                    continue
                if (
                    abs(x_m[a, v] - x_m[a, i]) < half_length_m[a, i] + half_length_m[a, v]
                    and abs(y_m[a, v] - y_m[a, i]) < half_width_m[a, i] + half_width_m[a, v]
                ):
                    collided[a, i] = True
                    break


@njit(cache=True, nogil=True)
def cars_ahead(
    x_m: np.ndarray,
    speed: np.ndarray,
    lane: np.ndarray,
    target_lane: np.ndarray,
    active: np.ndarray,
    half_length: np.ndarray,
    agents: int,
    gap_m: np.ndarray,
    speed_ahead: np.ndarray,
) -> None:
    """Each agent's nearest vehicle in front, (A, N) into ``gap_m`` (bumper to bumper, inf
    where there is none) and ``speed_ahead`` (its speed; the agent's own where there is none):
    among the other active vehicles ahead that share a lane with the agent, current or target
    on either side (:func:`.ahead.cars_ahead`; of equal gaps the lowest column)."""
    arenas, vehicles = x_m.shape
    for a in range(arenas):
        for n in range(agents):
            own_lane, own_target = lane[a, n], target_lane[a, n]
            best, best_v = np.inf, 0
            for v in range(vehicles):
                if v == n or not active[a, v]:
                    continue
                dx = x_m[a, v] - x_m[a, n]
                if not dx > 0.0:
                    continue
                o_lane, o_target = lane[a, v], target_lane[a, v]
                shares = (o_lane == own_lane) | (o_lane == own_target)
                shares |= (o_target == own_lane) | (o_target == own_target)
                if not shares:
                    continue
                gap = dx - half_length[a, v] - half_length[a, n]
                if gap < best:
                    best, best_v = gap, v
            gap_m[a, n] = best
            speed_ahead[a, n] = speed[a, best_v] if best < np.inf else speed[a, n]


@njit(cache=True, nogil=True)
def side_clear(
    x_m: np.ndarray,
    speed: np.ndarray,
    half_length: np.ndarray,
    active: np.ndarray,
    lane: np.ndarray,
    target_lane: np.ndarray,
    agents: int,
    clear_ahead_m: float,
    clear_behind_m: float,
    closing_time_s: float,
) -> np.ndarray:
    """(A, N, 2) bool: whether the lane to each agent's right [0] and left [1] is free of
    active vehicles in it or moving into it, within the agent's window ahead and behind, each
    grown by the closing speed times ``closing_time_s``; (A, V) inputs.

    What :meth:`.assist.LaneChangeAssist.side_clear` returns."""
    arenas, vehicles = x_m.shape
    clear = np.ones((arenas, agents, 2), dtype=np.bool_)
    for a in range(arenas):
        for i in range(agents):
            right, left = lane[a, i] - 1, lane[a, i] + 1
            for o in range(vehicles):
                if o == i or not active[a, o]:
                    continue
                in_right = lane[a, o] == right or target_lane[a, o] == right
                in_left = lane[a, o] == left or target_lane[a, o] == left
                if not (in_right or in_left):
                    continue
                dx = x_m[a, o] - x_m[a, i]
                reach = half_length[a, o] + half_length[a, i]
                # Positive when the other car gains on the agent from behind (or the agent
                # on a car ahead): the gap it needs grows with that speed.
                closing = speed[a, o] - speed[a, i]
                ahead = clear_ahead_m + max(-closing, 0.0) * closing_time_s
                behind = clear_behind_m + max(closing, 0.0) * closing_time_s
                if dx - reach < ahead and -dx - reach < behind:
                    if in_right:
                        clear[a, i, 0] = False
                    if in_left:
                        clear[a, i, 1] = False
    return clear


@njit(cache=True, nogil=True)
def unsafe_changes(
    x_m: np.ndarray,
    speed: np.ndarray,
    half_length: np.ndarray,
    active: np.ndarray,
    lane: np.ndarray,
    target_lane: np.ndarray,
    agents: int,
    response_s: float,
    brake_mps2: float,
    min_gap_m: float,
    unsafe: np.ndarray,
) -> None:
    """Into ``unsafe`` (A, N): the agents changing lanes whose target lane is not safe now
    (:class:`.lane_watch.LaneChangeWatch`): some other active vehicle in it or moving into it
    is nearer, bumper to bumper, than ``min_gap_m`` plus what the closing speed covers in
    ``response_s`` and in braking it away at ``brake_mps2``, the follower of the two closing
    in; a vehicle alongside is always too near."""
    arenas, vehicles = x_m.shape
    for a in range(arenas):
        for i in range(agents):
            unsafe[a, i] = False
            target = target_lane[a, i]
            if not active[a, i] or target == lane[a, i]:
                continue
            for v in range(vehicles):
                if v == i or not active[a, v]:
                    continue
                if lane[a, v] != target and target_lane[a, v] != target:
                    continue
                dx = x_m[a, v] - x_m[a, i]
                gap = abs(dx) - half_length[a, v] - half_length[a, i]
                # The follower of the two: the agent behind a car ahead, a car behind the agent.
                closing = speed[a, i] - speed[a, v] if dx >= 0.0 else speed[a, v] - speed[a, i]
                needed = min_gap_m
                if closing > 0.0:
                    needed += closing * response_s + closing * closing / (2.0 * brake_mps2)
                if gap < needed:
                    unsafe[a, i] = True
                    break


@njit(cache=True, nogil=True)
def track_passes(x, active, ahead, credited, every_pass, undo, stepped, gained, undone, passed):
    """:meth:`.overtakes.OvertakeTracker.track` car by car, compiled: for each agent ``k`` and each
    live car ``v`` (not itself), whether ``v`` went from ahead of it to behind it (an
    overtake, counted where not credited already, or every time) or the other way (a pass
    of the agent, taking back a credited overtake where ``undo``); ``ahead`` becomes now's."""
    arenas, agents, cars = ahead.shape
    for a in range(arenas):
        if not stepped[a]:
            continue
        for k in range(agents):
            for v in range(cars):
                ahead_now = x[a, v] > x[a, k]
                if active[a, v] and v != k:
                    if ahead[a, k, v] and not ahead_now:
                        if every_pass or not credited[a, k, v]:
                            gained[a, k] += 1
                        credited[a, k, v] = True
                    elif not ahead[a, k, v] and ahead_now:
                        passed[a, k] += 1
                        if undo and credited[a, k, v]:
                            undone[a, k] += 1
                            credited[a, k, v] = False
                ahead[a, k, v] = ahead_now


@njit(cache=True, nogil=True)
def close_episodes(
    rows: np.ndarray,
    reward: np.ndarray,
    lane_changes: np.ndarray,
    collided: np.ndarray,
    overtakes: np.ndarray,
    emergency_brakes: np.ndarray,
    active: np.ndarray,
    agent_decisions: np.ndarray,
    distance_m: np.ndarray,
    max_decisions: int,
    max_distance_m: float,
    episode_return: np.ndarray,
    lane_changes_total: np.ndarray,
    collisions_total: np.ndarray,
    overtakes_total: np.ndarray,
    emergency_brakes_total: np.ndarray,
    traffic_cars_sum: np.ndarray,
    truncated: np.ndarray,
) -> None:
    """Add one decision's events (R, N) of the arenas ``rows`` (R,) to their episodes' totals
    (A, N), count the traffic on their roads, and mark in ``truncated`` (R, N) the episodes at
    their decision limit or their distance (``max_distance_m``: inf for none). The arithmetic
    of :meth:`.episodes.EpisodeBook.close_decision`."""
    agents = reward.shape[1]
    vehicles = active.shape[1]
    for r in range(rows.size):
        a = rows[r]
        cars = 0
        for v in range(agents, vehicles):
            cars += active[a, v]
        for i in range(agents):
            episode_return[a, i] += reward[r, i]
            lane_changes_total[a, i] += lane_changes[r, i]
            collisions_total[a, i] += collided[r, i]
            overtakes_total[a, i] += overtakes[r, i]
            emergency_brakes_total[a, i] += emergency_brakes[r, i]
            traffic_cars_sum[a, i] += cars
            truncated[r, i] = (
                agent_decisions[a, i] >= max_decisions or distance_m[a, i] >= max_distance_m
            )


@njit(cache=True, nogil=True)
def fill_metrics(
    decisions, distance_m, lane_changes, overtakes, collisions, brakes, episode_return,
    traffic_cars_sum, aborts, decision_period_s, kmh, watch, table,
):  # fmt: skip
    """The columns of :meth:`.episodes.Episodes.metrics_table` in METRIC_FIELDS' order (then
    WATCH_METRICS' where ``watch``): the average speed over the decisions' time and the
    traffic per decision where a decision was taken (0 before), the counts as they are."""
    arenas, agents = decisions.shape
    for a in range(arenas):
        for k in range(agents):
            d = decisions[a, k]
            row = table[a, k]
            row[0] = distance_m[a, k] / (d * decision_period_s) / kmh if d > 0 else 0.0
            row[1] = lane_changes[a, k]
            row[2] = overtakes[a, k]
            row[3] = collisions[a, k]
            row[4] = brakes[a, k]
            row[5] = distance_m[a, k]
            row[6] = episode_return[a, k]
            row[7] = d
            row[8] = traffic_cars_sum[a, k] / d if d > 0 else 0.0
            if watch:
                row[9] = aborts[a, k]
