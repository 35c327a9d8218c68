"""Compiled loops (numba) for the simulation's inner work where numpy pays per call.

Each kernel replaces a run of whole-array numpy calls whose temporaries and per-call overhead
dominated a decision (one arena: dozens of calls on arrays of a few dozen elements; 64 arenas:
several passes over every camera pixel). They did the same float operations in the same order
as the numpy code they replaced, so results stayed bit for bit the same (``tests/test_golden.py``
was not re-recorded); they are now the only implementation of that arithmetic.

Compiled on first use and cached on disk (``cache=True``: next to this file, or under
``NUMBA_CACHE_DIR`` where that is not writable); the first decision of a fresh install pays the
compile (``bench/RESULTS.md`` states the figure), later processes load the cache. With
``NUMBA_DISABLE_JIT=1`` they run as plain Python (slow, for debugging).
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def lidar_scan(
    origin_x: np.ndarray,
    origin_y: np.ndarray,
    heading: np.ndarray,
    cos_h: np.ndarray,
    sin_h: np.ndarray,
    rel_x: np.ndarray,
    rel_y: np.ndarray,
    half_length: np.ndarray,
    half_width: np.ndarray,
    visible: np.ndarray,
    centre: np.ndarray,
    corner_angle: np.ndarray,
    ray_cos: np.ndarray,
    ray_sin: np.ndarray,
    rail_left_y: float,
    rail_right_y: float,
    max_range_m: float,
    dist: np.ndarray,
) -> None:
    """The LIDAR's distances (O, R) into ``dist`` (float32): the guard rails, then each
    visible car box (``rel_x``/``rel_y`` (O, V) relative to its observer) intersected with only
    the rays its angular extent covers, the nearest hit kept (0 from inside a box).

    The bearings of the cars' centres (``centre`` (O, V)) and corners (``corner_angle``
    (O, V, 4)) come in from numpy's arctan2, whose rounding (SIMD on some CPUs) a compiled
    arctan2 would not match bit for bit; ``cos_h``/``sin_h`` likewise. See
    :meth:`.sensors.lidar.Lidar.scan`.
    """
    observers, vehicles = rel_x.shape
    rays = ray_cos.shape[0]
    step = 2.0 * np.pi / rays
    max_range_sq = max_range_m**2
    ray_dx = np.empty(rays)
    ray_dy = np.empty(rays)
    best = np.empty(rays)
    for o in range(observers):
        for r in range(rays):
            dx = cos_h[o] * ray_cos[r] - sin_h[o] * ray_sin[r]
            dy = sin_h[o] * ray_cos[r] + cos_h[o] * ray_sin[r]
            ray_dx[r], ray_dy[r] = dx, dy
            # Guard rails: the rail on the side the ray points to (a ray exactly along the
            # road gets a vanishing sideways component and so an out-of-range distance).
            safe_dy = 1e-12 if abs(dy) < 1e-12 else dy
            rail_y = rail_left_y if safe_dy > 0.0 else rail_right_y
            best[r] = min((rail_y - origin_y[o]) / safe_dy, max_range_m)
        for v in range(vehicles):
            if not visible[o, v]:
                continue
            x_lo, x_hi = rel_x[o, v] - half_length[o, v], rel_x[o, v] + half_length[o, v]
            y_lo, y_hi = rel_y[o, v] - half_width[o, v], rel_y[o, v] + half_width[o, v]
            near_x = max(x_lo, min(0.0, x_hi))  # the box's nearest point
            near_y = max(y_lo, min(0.0, y_hi))
            if near_x * near_x + near_y * near_y > max_range_sq:
                continue
            if near_x == 0.0 and near_y == 0.0:
                first, count = 0, rays  # inside the box: every ray
            else:
                # Angular extent: the corners' bearings relative to the centre's (wrapped, so a
                # car behind, across the +-pi seam, is handled like any other).
                lo, hi = np.inf, -np.inf
                for k in range(4):
                    offset = (corner_angle[o, v, k] - centre[o, v] + np.pi) % (2.0 * np.pi) - np.pi
                    lo, hi = min(lo, offset), max(hi, offset)
                relative = (centre[o, v] - heading[o]) / step
                first = int(np.ceil(relative + lo / step))
                last = int(np.floor(relative + hi / step))
                count = min(max(last - first + 1, 0), rays)
            for j in range(count):
                ray = (first + j) % rays
                # A ray exactly parallel to a slab: a tiny component keeps the test exact
                # enough (the hit moves by far less than a millimetre) without 0/0.
                dx = ray_dx[ray]
                dy = ray_dy[ray]
                if dx == 0.0:
                    dx = 1e-12
                if dy == 0.0:
                    dy = 1e-12
                tx1, tx2 = x_lo / dx, x_hi / dx
                ty1, ty2 = y_lo / dy, y_hi / dy
                enter = max(min(tx1, tx2), min(ty1, ty2))
                leave = min(max(tx1, tx2), max(ty1, ty2))
                if leave >= enter and leave >= 0.0:
                    hit = max(enter, 0.0)
                    if hit < best[ray]:
                        best[ray] = hit
        for r in range(rays):
            dist[o, r] = best[r]


@njit(cache=True, nogil=True)
def paint_ground(
    image: np.ndarray,
    first_row: int,
    lanes: np.ndarray,
    line_half: np.ndarray,
    gap: np.ndarray,
    half_road: np.float32,
    shoulder_edge: np.float32,
    line_edge: np.float32,
    inner_edge: np.float32,
    values: np.ndarray,
) -> None:
    """Shade the ground rows of ``image`` (O, H, W) uint8 from ``lanes`` (O, R, W) float32,
    each ground pixel's position across the road in lane widths from the right edge.

    ``values``: the grass, shoulder, road and marking values (grey levels or classes);
    ``line_half`` (R, W) float32: a lane line's half width per pixel; ``gap`` (O, R) bool: rows
    that meet the road between two dashes; the edges: the road's half width, the shoulder's
    edge, the outer lines' outer edge and the inner lines' (all lane widths from the middle).
    """
    grass, shoulder, road, marking = values[0], values[1], values[2], values[3]
    observers, rows, width = lanes.shape
    for o in range(observers):
        for r in range(rows):
            row_gap = gap[o, r]
            out = image[o, first_row + r]
            for c in range(width):
                lane = lanes[o, r, c]
                from_middle = abs(lane - half_road)
                near_line = (
                    abs(lane - np.rint(lane)) <= line_half[r, c] and from_middle <= line_edge
                )
                if near_line and row_gap and from_middle < inner_edge:
                    near_line = False
                if near_line:
                    out[c] = marking
                elif from_middle <= half_road:
                    out[c] = road
                elif from_middle <= shoulder_edge:
                    out[c] = shoulder
                else:
                    out[c] = grass


@njit(cache=True, nogil=True)
def paint_boxes(
    image: np.ndarray,
    shown: np.ndarray,
    row_lo: np.ndarray,
    row_hi: np.ndarray,
    col_lo: np.ndarray,
    col_hi: np.ndarray,
    value: np.uint8,
) -> None:
    """Fill each shown (O, K) car's screen rectangle, inclusive pixel bounds (float, whole
    numbers, possibly off screen), with ``value`` in ``image`` (O, H, W) uint8."""
    observers, cars = shown.shape
    height, width = image.shape[1], image.shape[2]
    for o in range(observers):
        for k in range(cars):
            if not shown[o, k]:
                continue
            r0 = max(row_lo[o, k], 0.0)
            r1 = min(row_hi[o, k], height - 1.0)
            c0 = max(col_lo[o, k], 0.0)
            c1 = min(col_hi[o, k], width - 1.0)
            if r0 > r1 or c0 > c1:
                continue
            for r in range(int(r0), int(r1) + 1):
                for c in range(int(c0), int(c1) + 1):
                    image[o, r, c] = value


@njit(cache=True, nogil=True)
def follow_and_accelerate(
    x_m: np.ndarray,
    speed: np.ndarray,
    desired_speed: np.ndarray,
    lead: np.ndarray,
    valid: np.ndarray,
    half_length: np.ndarray,
    headway: np.ndarray,
    min_gap: np.ndarray,
    max_accel: np.ndarray,
    two_sqrt_ab: np.ndarray,
    agents: int,
    cruise: np.ndarray,
    aeb: np.ndarray,
    max_decel_mps2: float,
    no_gap_m: float,
    gap: np.ndarray,
    leader: np.ndarray,
    has_leader: np.ndarray,
    leader_speed: np.ndarray,
    closing: np.ndarray,
    accel: np.ndarray,
) -> None:
    """One frame's car-following of every vehicle, (A, V) arrays: whom it follows (the nearer
    of its two lane entries' leaders, ``lead``/``valid`` (A, 2V) flat indices) into ``gap``,
    ``leader``, ``has_leader``, ``leader_speed`` and ``closing``, and its acceleration into
    ``accel``: the IDM (agents without a free-road term), the agents' cruise control
    (``cruise``: time constant, comfortable deceleration, maximum acceleration) and emergency
    braking (``aeb``: time to collision, deceleration), within the vehicle's limits.

    The settings are :class:`.assist.CruiseControl`'s and :class:`.assist.EmergencyBraking`'s,
    the IDM :func:`idm`.
    """
    arenas, vehicles = x_m.shape
    time_constant_s, comfort_decel, cruise_max_accel = cruise[0], cruise[1], cruise[2]
    time_to_collision_s, aeb_decel = aeb[0], aeb[1]
    for a in range(arenas):
        origin = x_m[a, 0]
        for v in range(vehicles):
            front = (x_m[a, v] - origin) + half_length[a, v]
            first = no_gap_m
            second = no_gap_m
            if valid[a, v]:
                k = lead[a, v]
                c = k - a * vehicles
                first = ((x_m[a, c] - origin) - half_length[a, c]) - front
            if valid[a, vehicles + v]:
                k = lead[a, vehicles + v]
                c = k - a * vehicles
                second = ((x_m[a, c] - origin) - half_length[a, c]) - front
            g = min(first, second)
            k = lead[a, vehicles + v] if second < first else lead[a, v]
            own = speed[a, v]
            followed = speed[a, k - a * vehicles] if g < no_gap_m else own
            close = own - followed
            gap[a, v] = g
            leader[a, v] = k
            has_leader[a, v] = g < no_gap_m
            leader_speed[a, v] = followed
            closing[a, v] = close
            # IDM: agents' desired speed is infinite (their cruise control drives them).
            acc = idm(
                own,
                np.inf if v < agents else desired_speed[a, v],
                g,
                close,
                headway[a, v],
                min_gap[a, v],
                max_accel[a, v],
                two_sqrt_ab[a, v],
            )
            if v < agents:
                towards = min(
                    max((desired_speed[a, v] - own) / time_constant_s, -comfort_decel),
                    cruise_max_accel,
                )
                acc = min(towards, acc)
                if close > 0.0 and g < close * time_to_collision_s:
                    acc = min(acc, -aeb_decel)
            accel[a, v] = max(min(acc, max_accel[a, v]), -max_decel_mps2)


@njit(cache=True, nogil=True)
def capped_speeds(
    speed: np.ndarray,
    accel: np.ndarray,
    gap: np.ndarray,
    leader: np.ndarray,
    has_leader: np.ndarray,
    leader_speed: np.ndarray,
    is_traffic: np.ndarray,
    yield_to_agents: bool,
    max_decel_mps2: float,
    dt: float,
    new_speed: np.ndarray,
) -> None:
    """Every vehicle's speed at the end of the frame into ``new_speed`` (A, V): ``accel``
    integrated, not below 0, and for traffic behind a traffic leader (any leader with
    ``yield_to_agents``) no faster than keeps it 0.2 m behind that leader through the frame
    even if the leader brakes as hard as it can (the safety rule;
    :meth:`.physics.Physics.frame`). Both move at the mean of their old and new speeds
    (:func:`integrate`), so the follower closes in by ``(v + s) / 2 * dt`` against the
    leader's ``(u - max_decel * dt / 2) * dt``."""
    arenas, vehicles = speed.shape
    for a in range(arenas):
        for v in range(vehicles):
            s = max(speed[a, v] + accel[a, v] * dt, 0.0)
            if is_traffic[a, v] and has_leader[a, v]:
                c = leader[a, v] - a * vehicles
                if yield_to_agents or is_traffic[a, c]:
                    cap = (
                        2.0 * (gap[a, v] - 0.2) / dt
                        + 2.0 * leader_speed[a, v]
                        - max_decel_mps2 * dt
                        - speed[a, v]
                    )
                    s = min(s, max(cap, 0.0))
            new_speed[a, v] = s


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
    on either side (:meth:`.assist.DriverWarnings.cars_ahead`; of equal gaps the lowest
    column)."""
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
def colour(classes: np.ndarray, palette: np.ndarray) -> np.ndarray:
    """(O, H, W, 3) uint8: each pixel's surface class (O, H, W) looked up in ``palette``."""
    observers, height, width = classes.shape
    image = np.empty((observers, height, width, 3), dtype=np.uint8)
    for o in range(observers):
        for r in range(height):
            for c in range(width):
                k = classes[o, r, c]
                image[o, r, c, 0] = palette[k, 0]
                image[o, r, c, 1] = palette[k, 1]
                image[o, r, c, 2] = palette[k, 2]
    return image


@njit(cache=True, nogil=True)
def lidar_grid(
    distance: np.ndarray,
    ray_cos: np.ndarray,
    ray_sin: np.ndarray,
    hit_below_m: float,
    ahead_m: float,
    half_width_m: float,
    row_m: float,
    column_m: float,
    cells: int,
) -> np.ndarray:
    """(O, cells * cells) uint8: 255 in each cell of the car-centred grid that a ray's hit
    (``distance`` (O, R) below ``hit_below_m``) falls in, rows from ``ahead_m`` in front
    backwards, columns from ``half_width_m`` on the left rightwards
    (:class:`.sensors.lidar_map.LidarMap`)."""
    observers, rays = distance.shape
    image = np.zeros((observers, cells * cells), dtype=np.uint8)
    for o in range(observers):
        for r in range(rays):
            d = np.float64(distance[o, r])
            if not d < hit_below_m:
                continue
            row = np.floor((ahead_m - d * ray_cos[r]) / row_m)
            column = np.floor((half_width_m - d * ray_sin[r]) / column_m)
            if 0 <= row < cells and 0 <= column < cells:
                image[o, int(row) * cells + int(column)] = 255
    return image


@njit(cache=True, nogil=True)
def idm(
    speed: float,
    desired_speed: float,
    gap: float,
    closing: float,
    headway: float,
    min_gap: float,
    max_accel: float,
    two_sqrt_ab: float,
) -> float:
    """One car's Intelligent Driver Model acceleration (m/s^2): ``closing`` is its speed minus
    its leader's, ``gap`` bumper to bumper (m), ``two_sqrt_ab`` 2 sqrt(max_accel * comfortable
    deceleration); the desired gap is :func:`.traffic.car_following.idm_desired_gap`'s."""
    desired_gap = min_gap + max(0.0, speed * headway + speed * closing / two_sqrt_ab)
    ratio = speed / desired_speed
    ratio *= ratio
    interaction = desired_gap / max(gap, 0.1)
    return max_accel * (1.0 - ratio * ratio - interaction * interaction)


@njit(cache=True, nogil=True)
def mobil_accept(
    flat: np.ndarray,
    new_lane_leader: np.ndarray,
    new_lane_follower: np.ndarray,
    old_lane_follower: np.ndarray,
    own_gap: np.ndarray,
    own_has_leader: np.ndarray,
    own_leader: np.ndarray,
    random_mover: np.ndarray,
    politeness: np.ndarray,
    threshold: np.ndarray,
    x: np.ndarray,
    speed: np.ndarray,
    desired_speed: np.ndarray,
    accel: np.ndarray,
    headway: np.ndarray,
    min_gap: np.ndarray,
    max_accel: np.ndarray,
    two_sqrt_ab: np.ndarray,
    half_length: np.ndarray,
    safe_decel_mps2: float,
    no_gap_m: float,
) -> np.ndarray:
    """MOBIL's verdict for each candidate ``flat[i]`` (flat vehicle indices into the flattened
    (A, V) arrays ``x`` .. ``half_length``): its new lane's leader and follower and its old
    lane's follower (-1: none), its own gap, leader and whether it has one, whether it is a
    random mover, and its behaviour's politeness and threshold. True where the change is safe
    and worth it (or random and not braking hard).

    The arithmetic of :class:`.traffic.lane_changes.Mobil`, which gathers the neighbours."""
    accept = np.zeros(flat.size, dtype=np.bool_)
    for i in range(flat.size):
        c = flat[i]
        xc, vc, half = x[c], speed[c], half_length[c]
        nl = new_lane_leader[i]
        if nl >= 0:
            gap_new = ((x[nl] - xc) - half_length[nl]) - half
            closing_new = vc - speed[nl]
        else:
            gap_new = no_gap_m
            closing_new = 0.0
        accel_new = idm(
            vc,
            desired_speed[c],
            gap_new,
            closing_new,
            headway[c],
            min_gap[c],
            max_accel[c],
            two_sqrt_ab[c],
        )
        nf = new_lane_follower[i]
        nf_gain = 0.0
        gap_nf = no_gap_m
        nf_brakes_hard = False
        if nf >= 0:
            gap_nf = ((xc - x[nf]) - half) - half_length[nf]
            nf_accel_new = idm(
                speed[nf],
                desired_speed[nf],
                gap_nf,
                speed[nf] - vc,
                headway[nf],
                min_gap[nf],
                max_accel[nf],
                two_sqrt_ab[nf],
            )
            nf_gain = nf_accel_new - accel[nf]
            nf_brakes_hard = not (nf_accel_new >= -safe_decel_mps2)
        of = old_lane_follower[i]
        of_gain = 0.0
        if of >= 0:
            # The old follower would follow the old leader across the gap this car leaves.
            left_gap = own_gap[i] + 2 * half if own_has_leader[i] else no_gap_m
            of_gap_after = left_gap + (((xc - x[of]) - half) - half_length[of])
            ol_speed = speed[own_leader[i]] if own_has_leader[i] else speed[of]
            of_accel_after = idm(
                speed[of],
                desired_speed[of],
                of_gap_after,
                speed[of] - ol_speed,
                headway[of],
                min_gap[of],
                max_accel[of],
                two_sqrt_ab[of],
            )
            of_gain = of_accel_after - accel[of]
        safe = gap_new > min_gap[c] and gap_nf > min_gap[c] and not nf_brakes_hard
        incentive = (accel_new - accel[c]) + politeness[i] * (nf_gain + of_gain)
        # A change for no reason must not make the mover itself brake hard either.
        random = random_mover[i] and accel_new >= -safe_decel_mps2
        accept[i] = safe and (incentive > threshold[i] or random)
    return accept


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
