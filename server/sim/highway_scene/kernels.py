"""highway-env's scene, compiled: one call plays a decision of every arena.

What highway-env 1.12.1 does car by car in Python (``AbstractEnv._simulate``: for each frame
the controlled car takes its meta-action on the decision's first frame, every car acts, every
car steps, then pairs of cars are tested for collisions), done here by loops over arenas,
frames and cars in one numba function, on the simulator's structure-of-arrays state. The
formulas are highway-env's (module docstrings of :mod:`.config` give the files); the code is
this project's.

Coordinates are the simulator's: x along the road, y across it from the right edge, lane 0
the rightmost, headings positive to the left. highway-env's y grows to the right (its lane 0
is the leftmost): every rule here is the mirror image of its own, which changes nothing but
the side names (its LANE_LEFT is towards a higher lane number here), and where it breaks a tie
by the lower index of its lanes, the higher lane number here does.

The helpers are inlined into :func:`play_decision` (``inline="always"``): called, each would be
passed a dozen arrays (their shapes, strides and reference counts) for a few flops, and the
calls cost more than the work (about a fifth of a decision, measured).
"""

from __future__ import annotations

import functools
import itertools
import math
from concurrent.futures import ThreadPoolExecutor

import numba
import numpy as np
from numba import njit

# utils.not_zero's epsilon (highway-env).
_EPS = 1e-2
# Where a car marks a lane for its neighbours (road/road.py, neighbour_vehicles: on_lane with
# a margin of 1 m beyond the half width).
_NEIGHBOUR_MARGIN_M = 1.0

# The parameters the kernel reads, in one float64 array (the order of P_*).
(
    P_LANE_WIDTH,
    P_SPEED_LIMIT,
    P_MAX_SPEED,
    P_LENGTH,
    P_WIDTH,
    P_KP_A,
    P_KP_HEADING,
    P_KP_LATERAL,
    P_TAU_PURSUIT,
    P_MAX_STEERING,
    P_ACC_MAX,
    P_COMFORT_ACC,
    P_COMFORT_DEC,
    P_DISTANCE_WANTED,
    P_TIME_WANTED,
    P_POLITENESS,
    P_MIN_GAIN,
    P_MAX_BRAKING,
    P_CHANGE_DELAY,
    P_CHECK_ALL,
    P_AGENTS_IDM,
    P_COUNT,
) = range(22)
# Flags ride in the parameters (1.0 on): CPython compiles a call of over 30 arguments with *args,
# which numba cannot inline.

# The simulator's actions (protocol vocabulary: keep, cruise up, cruise down, left, right) as
# highway-env's meta-actions: IDLE, FASTER, SLOWER, LANE_LEFT, LANE_RIGHT.
A_KEEP, A_FASTER, A_SLOWER, A_LEFT, A_RIGHT = 0, 1, 2, 3, 4


@njit(cache=True, nogil=True, inline="always")
def not_zero(x: float) -> float:
    if abs(x) > _EPS:
        return x
    return _EPS if x >= 0.0 else -_EPS


@njit(cache=True, nogil=True, inline="always")
def wrap_to_pi(x: float) -> float:
    return ((x + math.pi) % (2.0 * math.pi)) - math.pi


@njit(cache=True, nogil=True, inline="always")
def lane_centre(lane: int, p: np.ndarray) -> float:
    return (lane + 0.5) * p[P_LANE_WIDTH]


@njit(cache=True, nogil=True, inline="always")
def closest_lane(y: float, lanes: int, p: np.ndarray) -> int:
    """road.py's get_closest_lane_index on a straight road: the nearest lane centre, a tie
    going to highway-env's lower index (the higher lane here)."""
    best, best_d = lanes - 1, abs(y - lane_centre(lanes - 1, p))
    for lane in range(lanes - 2, -1, -1):
        d = abs(y - lane_centre(lane, p))
        if d < best_d:
            best, best_d = lane, d
    return best


@njit(cache=True, nogil=True, inline="always")
def lane_members(a, x, y, active, lanes, p, members, counts):
    """Which cars mark each lane for their neighbours now (road.py, neighbour_vehicles: the
    cars within the lane's half width and a metre of its centre, so that a car between two
    lanes is in both): ``members[lane, :counts[lane]]``, in column order. Nothing a frame's
    acts change moves a car, so one list serves every car's acts in the frame."""
    reach = p[P_LANE_WIDTH] / 2.0 + _NEIGHBOUR_MARGIN_M
    for lane in range(lanes):
        counts[lane] = 0
    for v in range(x.shape[1]):
        if not active[a, v]:
            continue
        for lane in range(lanes):
            if not abs(y[a, v] - lane_centre(lane, p)) > reach:
                members[lane, counts[lane]] = v
                counts[lane] += 1


@njit(cache=True, nogil=True, inline="always")
def neighbours(a, i, lane, x, members, counts):
    """road.py's neighbour_vehicles of car ``i`` on ``lane``: the nearest car ahead (at the
    same position or further) and behind among the lane's members (:func:`lane_members`,
    in column order, as highway-env goes through its cars); -1 where there is none."""
    s = x[a, i]
    front, rear = -1, -1
    # Infinite bounds make the first candidate win, as highway-env's None does.
    s_front, s_rear = math.inf, -math.inf
    for m in range(counts[lane]):
        v = members[lane, m]
        s_v = x[a, v]
        if v != i:
            if s <= s_v <= s_front:
                front, s_front = v, s_v
            elif s_rear < s_v < s:
                rear, s_rear = v, s_v
    return front, rear


@njit(cache=True, nogil=True, inline="always")
def desired_gap(a, ego, front, x, speed, heading, p) -> float:
    """behavior.py's desired_gap (projected): the IDM's desired distance, centre to centre."""
    v = speed[a, ego]
    if heading[a, ego] == 0.0 and heading[a, front] == 0.0:
        # Both along the road (most pairs): the same number without the trigonometry.
        dv = v - speed[a, front]
    else:
        ch, sh = math.cos(heading[a, ego]), math.sin(heading[a, ego])
        dvx = v * ch - speed[a, front] * math.cos(heading[a, front])
        dvy = v * sh - speed[a, front] * math.sin(heading[a, front])
        dv = dvx * ch + dvy * sh
    ab = -p[P_COMFORT_ACC] * p[P_COMFORT_DEC]
    return p[P_DISTANCE_WANTED] + v * p[P_TIME_WANTED] + v * dv / (2.0 * math.sqrt(ab))


@njit(cache=True, nogil=True, inline="always")
def idm(a, ego, front, delta, x, speed, heading, target_speed, p) -> float:
    """behavior.py's acceleration: the IDM of car ``ego`` behind ``front`` (-1: none), with
    the exponent of the car that asks (``delta``); 0 for no car."""
    if ego < 0:
        return 0.0
    target = min(max(target_speed[a, ego], 0.0), p[P_SPEED_LIMIT])
    ratio = max(speed[a, ego], 0.0) / abs(not_zero(target))
    acceleration = p[P_COMFORT_ACC] * (1.0 - ratio**delta)
    if front >= 0:
        d = x[a, front] - x[a, ego]
        gap = desired_gap(a, ego, front, x, speed, heading, p) / not_zero(d)
        acceleration -= p[P_COMFORT_ACC] * gap * gap
    return acceleration


@njit(cache=True, nogil=True, inline="always")
def steering(a, i, target, y, speed, heading, p) -> float:
    """controller.py's steering_control on a straight lane: a lateral position controller, a
    heading controller, and the bicycle's steering angle for the heading rate wanted."""
    lateral = y[a, i] - lane_centre(target, p)
    if lateral == 0.0 and heading[a, i] == 0.0:
        return 0.0  # on the lane's centre line, along it: what the formulas give, exactly
    v = not_zero(speed[a, i])
    lateral_speed = -p[P_KP_LATERAL] * lateral
    heading_command = math.asin(min(max(lateral_speed / v, -1.0), 1.0))
    heading_ref = min(max(heading_command, -math.pi / 4), math.pi / 4)
    rate = p[P_KP_HEADING] * wrap_to_pi(heading_ref - heading[a, i])
    slip = math.asin(min(max(p[P_LENGTH] / 2.0 / v * rate, -1.0), 1.0))
    angle = math.atan(2.0 * math.tan(slip))
    return min(max(angle, -p[P_MAX_STEERING]), p[P_MAX_STEERING])


@njit(cache=True, nogil=True, inline="always")
def mobil(a, i, lane_to, old_front, old_rear, self_a, x, speed, heading, target_speed, delta,
          members, counts, p) -> bool:  # fmt: skip
    """behavior.py's mobil: is the change of car ``i`` into ``lane_to`` safe for its new
    follower, and worth at least the minimum gain (politeness weighing the others')? Its own
    lane's neighbours and IDM (``old_front``, ``old_rear``, ``self_a``) are the caller's, who
    needs them too; the others' accelerations are worked out only where politeness weighs
    them (highway-env's 0 times them adds nothing, exactly)."""
    d = delta[a, i]
    new_front, new_rear = neighbours(a, i, lane_to, x, members, counts)
    new_rear_pred_a = idm(a, new_rear, i, d, x, speed, heading, target_speed, p)
    if new_rear_pred_a < -p[P_MAX_BRAKING]:
        return False
    self_pred_a = idm(a, i, new_front, d, x, speed, heading, target_speed, p)
    jerk = self_pred_a - self_a
    if p[P_POLITENESS] != 0.0:
        new_rear_a = idm(a, new_rear, new_front, d, x, speed, heading, target_speed, p)
        old_rear_a = idm(a, old_rear, i, d, x, speed, heading, target_speed, p)
        old_rear_pred_a = idm(a, old_rear, old_front, d, x, speed, heading, target_speed, p)
        jerk += p[P_POLITENESS] * (new_rear_pred_a - new_rear_a + old_rear_pred_a - old_rear_a)
    return jerk >= p[P_MIN_GAIN]


@njit(cache=True, nogil=True, inline="always")
def change_lane_policy(
    a, i, lanes, old_front, old_rear, self_a, x, speed, heading, target_speed, delta, lane,
    target_lane, timer, active, members, counts, p,
) -> None:  # fmt: skip
    """behavior.py's change_lane_policy: a change under way is given up where another car is
    changing into the same lane just ahead; otherwise, once a LANE_CHANGE_DELAY, each side
    lane MOBIL recommends becomes the target (highway-env's left side first, the right one
    winning where both do)."""
    if lane[a, i] != target_lane[a, i]:
        goal = target_lane[a, i]
        for v in range(x.shape[1]):
            if v == i or not active[a, v] or lane[a, v] == goal or target_lane[a, v] != goal:
                continue
            d = x[a, v] - x[a, i]
            if 0.0 < d < desired_gap(a, i, v, x, speed, heading, p):
                target_lane[a, i] = lane[a, i]
                break
        return
    if not timer[a, i] > p[P_CHANGE_DELAY]:
        return
    timer[a, i] = 0.0
    here = lane[a, i]
    for side in (here + 1, here - 1):  # highway-env's id - 1 (left), then id + 1 (right)
        if side < 0 or side >= lanes or abs(speed[a, i]) < 1.0:
            continue
        if mobil(a, i, side, old_front, old_rear, self_a, x, speed, heading, target_speed,
                 delta, members, counts, p):  # fmt: skip
            target_lane[a, i] = side


@njit(cache=True, nogil=True, inline="always")
def _project(cx, cy, c, s, half_l, half_w, nx, ny):
    """The interval of a car's rectangle (centre, heading cos/sin, half sizes) on an axis."""
    lo, hi = 1e300, -1e300
    for sl in (-1.0, 1.0):
        for sw in (-1.0, 1.0):
            px = cx + c * sl * half_l - s * sw * half_w
            py = cy + s * sl * half_l + c * sw * half_w
            q = px * nx + py * ny
            lo = min(lo, q)
            hi = max(hi, q)
    return lo, hi


@njit(cache=True, nogil=True, inline="always")
def _interval_distance(min_a, max_a, min_b, max_b):
    return min_b - max_a if min_a < min_b else min_a - max_b


@njit(cache=True, nogil=True, inline="always")
def rectangles_meet(a, i, j, dt, x, y, speed, heading, p):
    """utils.py's are_polygons_intersecting for two cars' rectangles, car i's moved by the
    difference of their velocities over ``dt``: (intersecting, will intersect, translation x,
    translation y), the translation separating them along the axis of least overlap."""
    half_l, half_w = p[P_LENGTH] / 2.0, p[P_WIDTH] / 2.0
    ci, si = math.cos(heading[a, i]), math.sin(heading[a, i])
    cj, sj = math.cos(heading[a, j]), math.sin(heading[a, j])
    dx_disp = (speed[a, i] * ci - speed[a, j] * cj) * dt
    dy_disp = (speed[a, i] * si - speed[a, j] * sj) * dt
    centre_dx, centre_dy = x[a, i] - x[a, j], y[a, i] - y[a, j]
    intersecting = will = True
    min_distance = 1e300
    axis_x = axis_y = 0.0
    for owner in range(2):
        c, s = (ci, si) if owner == 0 else (cj, sj)
        for edge in range(4):
            # The normals of a rectangle's edges in highway-env's order (objects.py, polygon:
            # corners rear-right, rear-left, front-left, front-right): its two axes, each twice.
            if edge == 0:
                nx, ny = -c, -s
            elif edge == 1:
                nx, ny = -s, c
            elif edge == 2:
                nx, ny = c, s
            else:
                nx, ny = s, -c
            min_a, max_a = _project(x[a, i], y[a, i], ci, si, half_l, half_w, nx, ny)
            min_b, max_b = _project(x[a, j], y[a, j], cj, sj, half_l, half_w, nx, ny)
            if _interval_distance(min_a, max_a, min_b, max_b) > 0.0:
                intersecting = False
            projection = nx * dx_disp + ny * dy_disp
            if projection < 0.0:
                min_a += projection
            else:
                max_a += projection
            distance = _interval_distance(min_a, max_a, min_b, max_b)
            if distance > 0.0:
                will = False
            if not intersecting and not will:
                return False, False, 0.0, 0.0
            if abs(distance) < min_distance:
                min_distance = abs(distance)
                sign = 1.0 if centre_dx * nx + centre_dy * ny > 0.0 else -1.0
                axis_x, axis_y = sign * nx, sign * ny
    if will:
        return intersecting, will, min_distance * axis_x, min_distance * axis_y
    return intersecting, will, 0.0, 0.0


@njit(cache=True, nogil=True, inline="always")
def play_arena(
    a,
    x, y, speed, heading, lane, target_lane, target_speed, timer, delta, crashed,
    impact_x, impact_y, has_impact, active, agent_distance, speed_index,
    actions, target_speeds, agents, lanes, frames, dt, p,
    changes_started, steer, accel,
    members, counts, driven,
):  # fmt: skip
    """One decision of arena ``a`` (:func:`play_decision`); ``members`` and ``counts`` are
    scratch for :func:`lane_members`."""
    cars = x.shape[1]
    top = target_speeds.shape[0] - 1
    span = target_speeds[top] - target_speeds[0]
    diagonal = math.sqrt(p[P_LENGTH] ** 2 + p[P_WIDTH] ** 2)
    check_all = p[P_CHECK_ALL] != 0.0
    agents_idm = p[P_AGENTS_IDM] != 0.0
    for k in range(agents):
        changes_started[a, k] = False
        driven[a, k] = A_KEEP
        if not active[a, k] or agents_idm:
            continue
        action = actions[a, k]
        if action in (A_FASTER, A_SLOWER):
            # MDPVehicle.act: the index of the speed nearest the car's own, one up or down.
            ratio = (speed[a, k] - target_speeds[0]) / span
            index = int(min(max(np.round(ratio * top), 0.0), top))
            index = index + 1 if action == A_FASTER else index - 1
            speed_index[a, k] = min(max(index, 0), top)
            target_speed[a, k] = target_speeds[speed_index[a, k]]
        elif action in (A_LEFT, A_RIGHT):
            wanted = target_lane[a, k] + (1 if action == A_LEFT else -1)
            wanted = min(max(wanted, 0), lanes - 1)
            if wanted != target_lane[a, k]:
                target_lane[a, k] = wanted
                changes_started[a, k] = True
    for _ in range(frames):
        lane_members(a, x, y, active, lanes, p, members, counts)
        # Every car acts (road.py, Road.act): the agents' controllers; traffic's MOBIL,
        # steering and IDM (a crashed car does nothing: its step brakes it to a stop).
        for i in range(cars):
            if not active[a, i]:
                continue
            if i < agents and not agents_idm:
                steer[a, i] = steering(a, i, target_lane[a, i], y, speed, heading, p)
                accel[a, i] = p[P_KP_A] * (target_speed[a, i] - speed[a, i])
                continue
            if crashed[a, i]:
                continue
            # Its own lane's neighbours and IDM: MOBIL's and the IDM's below alike (nothing
            # moves in between).
            d = delta[a, i]
            front, rear = neighbours(a, i, lane[a, i], x, members, counts)
            acc = idm(a, i, front, d, x, speed, heading, target_speed, p)
            goal = target_lane[a, i]
            change_lane_policy(
                a, i, lanes, front, rear, acc, x, speed, heading, target_speed, delta,
                lane, target_lane, timer, active, members, counts, p,
            )  # fmt: skip
            if i < agents and target_lane[a, i] != goal and target_lane[a, i] != lane[a, i]:
                # An agent's car started a change: its meta-action (the decision's last one).
                changes_started[a, i] = True
                driven[a, i] = A_LEFT if target_lane[a, i] > lane[a, i] else A_RIGHT
            steer[a, i] = steering(a, i, target_lane[a, i], y, speed, heading, p)
            if lane[a, i] != target_lane[a, i]:
                front, _ = neighbours(a, i, target_lane[a, i], x, members, counts)
                acc = min(acc, idm(a, i, front, d, x, speed, heading, target_speed, p))
            accel[a, i] = min(max(acc, -p[P_ACC_MAX]), p[P_ACC_MAX])
        # Every car steps (kinematics.py, Vehicle.step: the bicycle model).
        for i in range(cars):
            if not active[a, i]:
                continue
            if i >= agents or agents_idm:
                timer[a, i] += dt
            angle, acc = steer[a, i], accel[a, i]
            if crashed[a, i]:
                angle, acc = 0.0, -speed[a, i]
            if speed[a, i] > p[P_MAX_SPEED]:
                acc = min(acc, p[P_MAX_SPEED] - speed[a, i])
            elif speed[a, i] < -p[P_MAX_SPEED]:
                acc = max(acc, -p[P_MAX_SPEED] - speed[a, i])
            before = x[a, i]
            beta = 0.0
            if angle == 0.0 and heading[a, i] == 0.0:
                # Straight along the road (most cars, most frames): the same numbers
                # without the trigonometry (cos 0 = 1, sin 0 = 0, atan(tan 0) = 0).
                x[a, i] += speed[a, i] * dt
            else:
                beta = math.atan(0.5 * math.tan(angle))
                x[a, i] += speed[a, i] * math.cos(heading[a, i] + beta) * dt
                y[a, i] += speed[a, i] * math.sin(heading[a, i] + beta) * dt
            if has_impact[a, i]:
                x[a, i] += impact_x[a, i]
                y[a, i] += impact_y[a, i]
                crashed[a, i] = True
                has_impact[a, i] = False
            heading[a, i] += speed[a, i] * math.sin(beta) / (p[P_LENGTH] / 2.0) * dt
            speed[a, i] += acc * dt
            lane[a, i] = closest_lane(y[a, i], lanes, p)
            if i < agents:
                agent_distance[a, i] += x[a, i] - before
        # Pairs of cars, each tested once (road.py, Road.step; objects.py).
        # Where only the controlled cars' collisions are tested, a pair's first car is one.
        for i in range(cars if check_all else agents):
            if not active[a, i]:
                continue
            for j in range(i + 1, cars):
                if not active[a, j]:
                    continue
                dx, dy = x[a, j] - x[a, i], y[a, j] - y[a, i]
                if math.sqrt(dx * dx + dy * dy) > diagonal + speed[a, i] * dt:
                    continue
                meet, will, tx, ty = rectangles_meet(a, i, j, dt, x, y, speed, heading, p)
                if will:
                    impact_x[a, i], impact_y[a, i] = tx / 2.0, ty / 2.0
                    impact_x[a, j], impact_y[a, j] = -tx / 2.0, -ty / 2.0
                    has_impact[a, i] = has_impact[a, j] = True
                if meet:
                    crashed[a, i] = crashed[a, j] = True
    if agents_idm:
        for k in range(agents):
            if not active[a, k] or changes_started[a, k]:
                continue
            # No change started: FASTER or SLOWER where the speed's nearest target speed
            # (MDPVehicle.speed_to_index) moved over the decision, IDLE where it did not.
            ratio = (speed[a, k] - target_speeds[0]) / span
            index = int(min(max(np.round(ratio * top), 0.0), top))
            if index > speed_index[a, k]:
                driven[a, k] = A_FASTER
            elif index < speed_index[a, k]:
                driven[a, k] = A_SLOWER
            speed_index[a, k] = index


# Compiled without numba's reference counting (_nrt=False): every helper inlined here takes
# arrays, and each would count a reference to each of them on the way in and out, atomically:
# half the decision's time, measured (21.4 -> 11.4 us per arena-decision). The decision
# allocates nothing (its scratch comes from the caller), which is what that asks.
@njit(cache=True, nogil=True, _nrt=False)  # type: ignore[call-overload]  # not in the stubs
def play_decision(
    x, y, speed, heading, lane, target_lane, target_speed, timer, delta, crashed,
    impact_x, impact_y, has_impact, active, agent_distance, speed_index,
    actions, target_speeds, agents, lanes, frames, dt, p,
    changes_started, steer, accel, members, counts, stepping, driven,
):  # fmt: skip
    """One decision of every arena where ``stepping`` (A,) (rows of the state arrays): the
    agents' meta-actions
    (``actions``, the simulator's action numbers), then ``frames`` frames of highway-env's
    act, step and collision test, every pair of cars tested where ``p[P_CHECK_ALL]``, only
    pairs with an agent's car otherwise. ``changes_started`` (A, N) is set where an agent's
    action changed its target lane. Scratch: ``steer`` and ``accel`` (A, V) float64, ``members``
    (A, lanes, V) and ``counts`` (A, lanes) int64.

    ``p[P_AGENTS_IDM]``: the agents' cars drive themselves as traffic does (IDMVehicle: IDM, MOBIL
    and its timer; ``actions`` are not read) and ``driven`` (A, N) says the meta-action each
    one's decision stands for: the lane change it started (the last one), else FASTER or
    SLOWER where the target speed nearest its speed (its ``speed_index``, kept so) rose or
    fell, else IDLE. Without it ``driven`` is IDLE throughout."""
    arenas = x.shape[0]
    for a in range(arenas):
        if not stepping[a]:
            continue
        play_arena(
            a, x, y, speed, heading, lane, target_lane, target_speed, timer, delta, crashed,
            impact_x, impact_y, has_impact, active, agent_distance, speed_index, actions,
            target_speeds, agents, lanes, frames, dt, p, changes_started, steer, accel,
            members[a], counts[a], driven,
        )  # fmt: skip


# Arenas in a block of the decision's threads: below twice this, one thread. Two threads cost
# about a fifth more CPU per step (the two vCPUs share a core's caches), and pay from 64 arenas
# of highway-fast on an idle 2-core machine: 76k agent-steps per wall-second against one
# thread's 68k (57k against 68k per CPU-second); at 256, 120k per wall-second (78k per CPU-s).
ARENAS_PER_THREAD_MIN = 32


def arena_blocks(arenas: int) -> list[slice]:
    """The arenas split into contiguous blocks, one per thread: numba's thread count
    (``NUMBA_NUM_THREADS``, every core by default), at least :data:`ARENAS_PER_THREAD_MIN`
    arenas each."""
    if arenas < 2 * ARENAS_PER_THREAD_MIN:
        return [slice(0, arenas)]  # the common case, without numpy's costs
    threads = max(1, min(numba.get_num_threads(), arenas // ARENAS_PER_THREAD_MIN))
    bounds = np.linspace(0, arenas, threads + 1).astype(int)
    return [slice(int(lo), int(hi)) for lo, hi in itertools.pairwise(bounds)]


@functools.cache
def thread_pool(workers: int) -> ThreadPoolExecutor:
    return ThreadPoolExecutor(max_workers=workers, thread_name_prefix="overtake-decision")
