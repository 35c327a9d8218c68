"""Car-following's compiled loops (numba): the IDM, every vehicle's acceleration in a frame
(traffic's car-following, the agents' cruise control and emergency braking), MOBIL's verdict,
and traffic's safety cap on speeds. Compiled and cached as
:mod:`overtake.server.sim.kernels` says.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True, nogil=True, inline="always")
def desired_gap(
    speed: float, closing: float, headway: float, min_gap: float, two_sqrt_ab: float
) -> float:
    """The IDM's desired bumper-to-bumper gap s* (m), as
    :func:`.traffic.car_following.idm_desired_gap` (the spawner's, in numpy)."""
    return min_gap + max(0.0, speed * headway + speed * closing / two_sqrt_ab)


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
    ratio = speed / desired_speed
    ratio *= ratio
    interaction = desired_gap(speed, closing, headway, min_gap, two_sqrt_ab) / max(gap, 0.1)
    return max_accel * (1.0 - ratio * ratio - interaction * interaction)


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
    steps: np.ndarray,
    gap: np.ndarray,
    leader: np.ndarray,
    has_leader: np.ndarray,
    leader_speed: np.ndarray,
    closing: np.ndarray,
    accel: np.ndarray,
    idm_accel: np.ndarray,
) -> None:
    """One frame's car-following of every vehicle, (A, V) arrays: whom it follows (the nearer
    of its two lane entries' leaders, ``lead``/``valid`` (A, 2V) flat indices) into ``gap``,
    ``leader``, ``has_leader``, ``leader_speed`` and ``closing``, and its acceleration into
    ``accel``: the IDM (agents without a free-road term), the agents' cruise control
    (``cruise``: time constant, comfortable deceleration, maximum acceleration) and emergency
    braking (``aeb``: time to collision, deceleration), within the vehicle's limits.

    ``steps`` (frame seconds, safety gap m, 1 where traffic yields to agents; a frame of 0
    keeps the IDM): traffic follows Ho's rule instead (``traffic.following =
    "speed_steps"``): its speed steps towards its desired speed by at most its maximum
    acceleration a frame, and with a vehicle ahead within the safety gap it does not speed up,
    and takes a slower one's speed at once (an agent's only where traffic yields to agents).
    ``idm_accel`` gets the IDM's (and the agents' assistance's) acceleration either way: what
    MOBIL weighs.

    The settings are :class:`.assist.CruiseControl`'s and :class:`.assist.EmergencyBraking`'s,
    the IDM :func:`idm`.
    """
    frame_s, safety_gap_m, yields = steps[0], steps[1], steps[2] > 0.0
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
            acc = max(min(acc, max_accel[a, v]), -max_decel_mps2)
            idm_accel[a, v] = acc
            if v >= agents and frame_s > 0.0:
                limit = max_accel[a, v]
                acc = min(max((desired_speed[a, v] - own) / frame_s, -limit), limit)
                if g < safety_gap_m:
                    acc = min(acc, 0.0)
                    if close > 0.0 and (yields or k - a * vehicles >= agents):
                        # Matched at once, however hard that brakes (his rule).
                        acc = -close / frame_s
            accel[a, v] = acc


@njit(cache=True, nogil=True, inline="always")
def _neighbours(
    sorted_keys: np.ndarray,
    sorted_group: np.ndarray,
    sorted_vehicle: np.ndarray,
    group: float,
    query: float,
) -> tuple[int, int]:
    """The vehicles just ahead of and just behind the key ``query`` in the lane ``group`` of a
    lane index (:class:`..lane_index.LaneIndex`), -1 where there is none: the first entry at
    or above the key (numpy's ``searchsorted(side="left")``), and the one before it."""
    size = sorted_keys.size
    lo, hi = 0, size
    while lo < hi:
        mid = (lo + hi) >> 1
        if sorted_keys[mid] < query:
            lo = mid + 1
        else:
            hi = mid
    ahead = sorted_vehicle[lo] if lo < size and sorted_group[lo] == group else -1
    behind = sorted_vehicle[lo - 1] if lo > 0 and sorted_group[lo - 1] == group else -1
    return ahead, behind


@njit(cache=True, nogil=True)
def mobil_decide(
    decisions: np.ndarray,
    is_candidate_kind: np.ndarray,
    kind: np.ndarray,
    active: np.ndarray,
    lane: np.ndarray,
    target_lane: np.ndarray,
    change_progress: np.ndarray,
    lane_count: int,
    sorted_keys: np.ndarray,
    sorted_group: np.ndarray,
    sorted_vehicle: np.ndarray,
    lanes_plus_one: int,
    key_span: float,
    key_offset: float,
    own_gap: np.ndarray,
    own_has_leader: np.ndarray,
    own_leader: np.ndarray,
    random_mover: np.ndarray,
    politeness_of_kind: np.ndarray,
    threshold_of_kind: np.ndarray,
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
    react_s: float,
) -> None:
    """Start the lane changes MOBIL accepts, in place (``target_lane``, ``change_progress``).

    Every array but ``decisions`` (A,) and the per-kind tables is a flattened (A, V) one;
    ``x`` is relative to each arena's first agent, as the lane index's keys are. A candidate
    is an active car of a traffic kind (``is_candidate_kind``) not changing lanes, whose lane
    on this decision's side (left on even decisions, right on odd ones) exists. Its new lane's
    leader and follower and its old lane's follower come from the lane index; then the change
    must be safe and worth it (or random and not braking hard): the arithmetic of
    :class:`.traffic.lane_changes.Mobil`."""
    arenas = decisions.size
    vehicles = x.size // arenas if arenas else 0
    for a in range(arenas):
        direction = 1 if decisions[a] % 2 == 0 else -1
        for v in range(vehicles):
            c = a * vehicles + v
            new_lane = lane[c] + direction
            if not (
                is_candidate_kind[kind[c]]
                and active[c]
                and target_lane[c] == lane[c]
                and new_lane >= 0
                and new_lane < lane_count
            ):
                continue
            xc, vc, half = x[c], speed[c], half_length[c]
            shifted = xc + key_offset
            group_new = a * float(lanes_plus_one) + new_lane
            nl, nf = _neighbours(
                sorted_keys, sorted_group, sorted_vehicle, group_new, group_new * key_span + shifted
            )
            group_old = a * float(lanes_plus_one) + lane[c]
            _, of = _neighbours(
                sorted_keys, sorted_group, sorted_vehicle, group_old, group_old * key_span + shifted
            )
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
            of_gain = 0.0
            if of >= 0:
                # The old follower would follow the old leader across the gap this car leaves.
                left_gap = own_gap[c] + 2 * half if own_has_leader[c] else no_gap_m
                of_gap_after = left_gap + (((xc - x[of]) - half) - half_length[of])
                ol_speed = speed[own_leader[c]] if own_has_leader[c] else speed[of]
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
            # The gaps must outlast ``react_s`` of closing in (Ho's followers react a frame
            # later).
            margin_new = min_gap[c] + max(closing_new, 0.0) * react_s
            margin_nf = min_gap[c] + (max(speed[nf] - vc, 0.0) * react_s if nf >= 0 else 0.0)
            safe = gap_new > margin_new and gap_nf > margin_nf and not nf_brakes_hard
            incentive = (accel_new - accel[c]) + politeness_of_kind[kind[c]] * (nf_gain + of_gain)
            # A change for no reason must not make the mover itself brake hard either.
            random = random_mover[c] and accel_new >= -safe_decel_mps2
            if safe and (incentive > threshold_of_kind[kind[c]] or random):
                target_lane[c] = new_lane
                change_progress[c] = 0.0


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
def random_manoeuvres(
    kind: np.ndarray,
    active: np.ndarray,
    speed: np.ndarray,
    own_speed: np.ndarray,
    desired_speed: np.ndarray,
    uniforms: np.ndarray,
    u_change: int,
    u_new_speed: int,
    u_random_lane: int,
    traffic_kinds: int,
    change_prob: np.ndarray,
    speed_lo: np.ndarray,
    speed_hi: np.ndarray,
    keeps_current: np.ndarray,
    walk_step: np.ndarray,
    walk_up: np.ndarray,
    walk_down: np.ndarray,
    walk_lo: np.ndarray,
    walk_hi: np.ndarray,
    random_lane_prob: np.ndarray,
    random_lane_when_slow: np.ndarray,
    movers: np.ndarray,
) -> None:
    """One decision's random manoeuvres of every traffic car (a kind below ``traffic_kinds``,
    on the road), in place on ``desired_speed`` (A, V): a new desired speed drawn with the
    kind's ``change_prob``, a holding kind's pace kept (``keeps_current``), a walking kind's
    step (``walk_step`` > 0); and ``movers`` (A, V) marks the cars that want a lane change
    whatever their incentive. Draws from ``uniforms`` (A, V, U) at the ``u_*`` columns, the
    per-kind tables indexed by ``kind``. The arithmetic of
    :class:`.traffic.manoeuvres.RandomManoeuvres`, car by car."""
    arenas, vehicles = kind.shape
    for a in range(arenas):
        for v in range(vehicles):
            k = kind[a, v]
            if not (k < traffic_kinds and active[a, v]):
                movers[a, v] = False
                continue
            u = uniforms[a, v]
            desired = desired_speed[a, v]
            if u[u_change] < change_prob[k]:
                desired = speed_lo[k] + u[u_new_speed] * (speed_hi[k] - speed_lo[k])
            if keeps_current[k]:
                desired = min(max(speed[a, v], own_speed[a, v]), walk_hi[k])
            if walk_step[k] > 0:
                draw, up = u[u_change], walk_up[k]
                up_step = 1.0 if draw < up else 0.0
                down_step = 1.0 if draw >= up and draw < up + walk_down[k] else 0.0
                step = walk_step[k] * (up_step - down_step)
                lo = walk_lo[k]
                if lo < 0.0:
                    lo = own_speed[a, v]
                desired = min(max(desired + step, lo), walk_hi[k])
            desired_speed[a, v] = desired
            # Ho's lane switcher tries only while slower than its own speed.
            movers[a, v] = u[u_random_lane] < random_lane_prob[k] and (
                not random_lane_when_slow[k] or speed[a, v] < own_speed[a, v]
            )
