"""Car-following: the Intelligent Driver Model (Treiber et al.), and whom each car follows.

Traffic follows its leader with an IDM of its behaviour's parameters; the agents' cruise
control (:mod:`..assist`) keeps the IDM's distance-keeping term and replaces its free-road term
with a speed controller towards the cruise target. Everything is vectorised over (arenas,
vehicles).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..lane_index import NO_GAP_M


def idm_accel(
    speed: np.ndarray,
    desired_speed: np.ndarray,
    gap: np.ndarray,
    closing_speed: np.ndarray,
    time_headway: np.ndarray,
    min_gap: np.ndarray,
    max_accel: np.ndarray,
    two_sqrt_ab: np.ndarray,
) -> np.ndarray:
    """Intelligent Driver Model acceleration (m/s^2); arguments broadcast against each other.

    ``closing_speed`` is own speed minus the leader's; ``gap`` is bumper to bumper (m);
    ``two_sqrt_ab`` is 2 * sqrt(max_accel * comfortable_decel), precomputed per vehicle.
    """
    desired_gap = idm_desired_gap(speed, closing_speed, time_headway, min_gap, two_sqrt_ab)
    ratio = speed / desired_speed
    ratio *= ratio
    interaction = desired_gap / np.maximum(gap, 0.1)
    return max_accel * (1.0 - ratio * ratio - interaction * interaction)


def idm_desired_gap(
    speed: np.ndarray,
    closing_speed: np.ndarray,
    time_headway: np.ndarray,
    min_gap: np.ndarray,
    two_sqrt_ab: np.ndarray,
) -> np.ndarray:
    """The IDM's desired bumper-to-bumper gap s* (m)."""
    return min_gap + np.maximum(0.0, speed * time_headway + speed * closing_speed / two_sqrt_ab)


# Built every frame: a plain record (a frozen one pays a setattr call per field).
@dataclass(slots=True)
class Following:
    """Whom each vehicle follows this frame, (A, V) each: the nearer of the leaders in its
    lane and, while it changes lanes, in its target lane."""

    gap_m: np.ndarray  # bumper to bumper; NO_GAP_M where nobody is ahead
    leader: np.ndarray  # flat index (arena * V + column) of the leader
    has_leader: np.ndarray  # bool
    leader_speed_mps: np.ndarray  # own speed where there is no leader
    closing_mps: np.ndarray  # own speed minus the leader's


def follow(
    x_rel: np.ndarray,
    half_length: np.ndarray,
    speed: np.ndarray,
    lead: np.ndarray,
    valid: np.ndarray,
) -> Following:
    """Gaps to the leaders of every lane entry (``lead``/``valid`` (A, 2V) from
    :func:`~overtake.server.sim.lane_index.leaders`), nearer of a vehicle's two entries."""
    vehicles = x_rel.shape[1]
    rear = (x_rel - half_length).reshape(-1)
    front = x_rel + half_length
    entry_gap = np.where(valid, rear[lead] - np.concatenate([front, front], axis=1), NO_GAP_M)
    first, second = entry_gap[:, :vehicles], entry_gap[:, vehicles:]
    gap = np.minimum(first, second)
    leader = np.where(second < first, lead[:, vehicles:], lead[:, :vehicles])  # flat index
    has_leader = gap < NO_GAP_M
    leader_speed = np.where(has_leader, speed.reshape(-1)[leader], speed)
    return Following(
        gap_m=gap,
        leader=leader,
        has_leader=has_leader,
        leader_speed_mps=leader_speed,
        closing_mps=speed - leader_speed,
    )
