"""highway-env's scene, compiled outside the decision: where the cars start
(``Vehicle.create_random``), which meta-actions can be taken and what each does, and the
reward (one call each, every arena). Coordinates and action numbers are :mod:`.kernels`'."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from .kernels import A_FASTER, A_KEEP, A_LEFT, A_RIGHT, A_SLOWER


@njit(cache=True, nogil=True)
def place_cars(
    rng, row, order, agents, lanes, lane_width, spacing_factor, ego_speed, ego_spacing,
    traffic_spacing, speed_limit, target_speeds, change_delay, delta_low, delta_high,
    agent_kind, x, y, speed, desired, lane, target_lane, active, kind, speed_index, timer,
    delta,
):  # fmt: skip
    """vehicle/kinematics.py's ``Vehicle.create_random``, car after car in ``order`` (column
    numbers), into row ``row`` of the state arrays: each car in a random lane, ahead of the
    foremost so far by its spacing. highway-env draws, for each car, the lane (its
    ``np_random.choice`` of the road's one start and end node draws nothing), then a traffic
    car's speed (the controlled car's is given), then the spacing's factor, then a traffic car's
    IDM exponent (``IDMVehicle.randomize_behavior``, envs/highway_env.py's _create_vehicles).
    Here a traffic car's speed is drawn before its lane: the same distributions, another road
    for the same seed."""
    top = target_speeds.shape[0] - 1
    foremost = 0.0
    for n_placed in range(order.shape[0]):
        column = order[n_placed]
        is_agent = column < agents
        if is_agent:
            v, spacing = ego_speed, ego_spacing
        else:
            v, spacing = rng.uniform(0.7 * speed_limit, 0.8 * speed_limit), traffic_spacing
        car_lane = lanes - 1 - rng.integers(0, lanes)
        offset = spacing * (12.0 + v) * spacing_factor
        at = 3.0 * offset if n_placed == 0 else foremost
        at += offset * rng.uniform(0.9, 1.1)
        foremost = at if n_placed == 0 else max(foremost, at)
        x[row, column] = at
        y[row, column] = (car_lane + 0.5) * lane_width
        lane[row, column] = target_lane[row, column] = car_lane
        speed[row, column] = desired[row, column] = v
        active[row, column] = True
        if is_agent:
            kind[row, column] = agent_kind
            # MDPVehicle.speed_to_index: the nearest of the evenly spaced target speeds.
            ratio = (v - target_speeds[0]) / (target_speeds[top] - target_speeds[0])
            index = int(min(max(np.round(ratio * top), 0.0), top))
            speed_index[row, column] = index
            desired[row, column] = target_speeds[index]
        else:
            # IDMVehicle's lane-change timer starts from its position (behavior.py), in
            # highway-env's coordinates, whose y grows from the left lane.
            y_highway_env = (lanes - 1 - car_lane) * lane_width
            timer[row, column] = ((at + y_highway_env) * math.pi) % change_delay
            delta[row, column] = rng.uniform(delta_low, delta_high)


@njit(cache=True, nogil=True)
def available(from_lane, speed_index, lanes, top, mask):
    """DiscreteMetaAction's get_available_actions for each agent into ``mask`` (A, N, 5):
    IDLE always, a lane change where there is a lane beyond ``from_lane`` (highway-env's: the
    lane the car is in), FASTER and SLOWER where the speed index can move."""
    arenas, agents = speed_index.shape
    for a in range(arenas):
        for k in range(agents):
            mask[a, k, A_KEEP] = 1
            mask[a, k, A_LEFT] = from_lane[a, k] < lanes - 1
            mask[a, k, A_RIGHT] = from_lane[a, k] > 0
            mask[a, k, A_FASTER] = speed_index[a, k] < top
            mask[a, k, A_SLOWER] = speed_index[a, k] > 0


@njit(cache=True, nogil=True)
def rewards(
    crashed, target_lane, lane, y, speed, heading, lanes, lane_width, low, high, weights,
    normalize, out, collision, right_lane, high_speed, on_road,
):  # fmt: skip
    """envs/highway_env.py's _rewards and _reward for each agent: the terms (into
    ``collision``, ``right_lane``, ``high_speed``, ``on_road``) and the reward (``out``): the
    weighted sum (``weights``: collision, right lane, high speed), normalised to [0, 1] where
    asked, times on-road."""
    arenas, agents = out.shape
    w_collision, w_right, w_fast = weights[0], weights[1], weights[2]
    for a in range(arenas):
        for k in range(agents):
            hit = 1.0 if crashed[a, k] else 0.0
            # highway-env's lane index of the target lane over the last: 1 on the right.
            right = (lanes - 1 - target_lane[a, k]) / max(lanes - 1, 1)
            forward = speed[a, k] * math.cos(heading[a, k])
            fast = min(max((forward - low) / (high - low), 0.0), 1.0)
            centre = (lane[a, k] + 0.5) * lane_width
            road = 1.0 if abs(y[a, k] - centre) <= lane_width / 2 else 0.0
            reward = w_collision * hit + w_right * right + w_fast * fast
            if normalize:
                reward = (reward - w_collision) / (w_fast + w_right - w_collision)
            out[a, k] = reward * road
            collision[a, k], right_lane[a, k], high_speed[a, k] = hit, right, fast
            on_road[a, k] = road


@njit(cache=True, nogil=True)
def applied_actions(mask, actions, applied):
    """What each agent's car does with its action (into ``applied``): the action where
    ``mask`` (what the car can do: :func:`available` from the lane it is changing into) allows
    it, IDLE otherwise (highway-env clips the target lane or the speed index)."""
    arenas, agents = actions.shape
    for a in range(arenas):
        for k in range(agents):
            action = actions[a, k]
            applied[a, k] = action if mask[a, k, action] == 1 else A_KEEP
